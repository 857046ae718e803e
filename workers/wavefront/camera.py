"""Pinhole look-at camera: primary rays for a pass's pixels and samples, starting at the
camera's near plane (so a camera on a surface does not see it at t = 0)."""

from __future__ import annotations

import numpy as np

from nprt.scene.model import Camera
from nprt.workers.kernels import quads
from nprt.workers.kernels.sampling import normalize


def camera_frame(cam: Camera, width: int, height: int) -> tuple:
    """eye, fwd, right, up (3,) float64 and the image plane's half width and height at
    unit distance (float)."""
    eye = np.asarray(cam.eye, np.float64)
    fwd = normalize((np.asarray(cam.target, np.float64) - eye)[None])[0]
    right = normalize(np.cross(fwd, np.asarray(cam.up, np.float64))[None])[0]
    up = np.cross(right, fwd)
    half_h = np.tan(np.radians(cam.fov_deg) / 2.0)
    half_w = half_h * width / height
    return eye, fwd, right, up, float(half_w), float(half_h)


def generate_primary(cam: Camera, width: int, height: int, seed: int,
                     pixel: np.ndarray, sample: np.ndarray):
    """Jittered camera rays (the kernel `nprt.workers.kernels.quads.camera_rays`).

    pixel, sample : (n,) uint32
    returns origin (n, 3) float64 (on the near plane), direction (n, 3) float32 unit
    """
    eye, fwd, right, up, half_w, half_h = camera_frame(cam, width, height)
    return quads.camera_rays(np.uint64(seed & 0xFFFFFFFFFFFFFFFF), width, height,
                             np.ascontiguousarray(pixel, np.uint32),
                             np.ascontiguousarray(sample, np.uint32), eye, fwd, right, up,
                             half_w, half_h, float(cam.near_distance))
