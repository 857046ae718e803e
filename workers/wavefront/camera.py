"""Pinhole look-at camera: primary rays for a pass's pixels and samples, starting at the
camera's near plane (so a camera on a surface does not see it at t = 0)."""

from __future__ import annotations

import numpy as np

from nprt.scene.model import Camera
from nprt.workers.kernels.rng import CAMERA_BOUNCE, uniform
from nprt.workers.kernels.sampling import normalize
from nprt.workers.wavefront.batch import ORIGIN_DTYPE


def generate_primary(cam: Camera, width: int, height: int, seed: int,
                     pixel: np.ndarray, sample: np.ndarray):
    """Jittered camera rays.

    pixel, sample : (n,) uint32
    returns origin (n, 3) float64 (on the near plane), direction (n, 3) float32 unit
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
    direction = normalize(d).astype(np.float32)
    # The near plane lies near_distance along fwd: the ray reaches it at near / cos.
    unit = direction.astype(np.float64)
    t_near = cam.near_distance / (unit @ fwd)  # (n,) float64, cos > 0 inside the frustum
    origin = eye[None] + t_near[:, None] * unit
    return origin.astype(ORIGIN_DTYPE), direction
