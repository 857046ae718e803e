"""Pinhole look-at camera: primary rays for a pass's pixels and samples."""

from __future__ import annotations

import numpy as np

from scene.model import Camera
from workers.rng import CAMERA_BOUNCE, uniform
from workers.sampling import normalize


def generate_primary(cam: Camera, width: int, height: int, seed: int,
                     pixel: np.ndarray, sample: np.ndarray):
    """Jittered camera rays.

    pixel, sample : (n,) uint32
    returns origin (n, 3) float32, direction (n, 3) float32 unit
    """
    eye = np.asarray(cam.eye, np.float64)
    fwd = normalize((np.asarray(cam.target, np.float64) - eye)[None])[0]
    right = normalize(np.cross(fwd, np.asarray(cam.up, np.float64))[None])[0]
    up = np.cross(right, fwd)
    half_h = np.tan(np.radians(cam.fov_deg) / 2.0)
    half_w = half_h * width / height
    jx = uniform(seed, pixel, sample, CAMERA_BOUNCE, 0)
    jy = uniform(seed, pixel, sample, CAMERA_BOUNCE, 1)
    x = (pixel % width + jx) / width * 2.0 - 1.0  # (n,) in [-1, 1], left to right
    y = 1.0 - (pixel // width + jy) / height * 2.0  # top row is +1
    d = fwd[None] + (x * half_w)[:, None] * right[None] + (y * half_h)[:, None] * up[None]
    origin = np.broadcast_to(eye.astype(np.float32), (len(pixel), 3)).copy()
    return origin, normalize(d).astype(np.float32)
