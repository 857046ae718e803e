"""Sampling kernels: orthonormal frames and the cosine-weighted hemisphere."""

from __future__ import annotations

import numpy as np


def normalize(v: np.ndarray) -> np.ndarray:
    """(n, 3) -> (n, 3) unit vectors; zero vectors stay zero."""
    length = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(length > 0, length, 1.0)


def frame(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tangent and bitangent for unit normals (n, 3) float64 (Duff et al. 2017, branchless)."""
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    s = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return t, s


def cosine_hemisphere(u1: np.ndarray, u2: np.ndarray, n: np.ndarray):
    """Cosine-weighted directions about unit normals.

    u1, u2 : (k,) float64 in [0, 1); n : (k, 3) float64
    returns direction (k, 3) float64 unit, pdf (k,) float64 solid-angle density cos/pi
    """
    r = np.sqrt(u1)
    phi = 2.0 * np.pi * u2
    x, y = r * np.cos(phi), r * np.sin(phi)
    z = np.sqrt(np.maximum(0.0, 1.0 - u1))
    t, s = frame(n)
    d = x[:, None] * t + y[:, None] * s + z[:, None] * n
    return d, z / np.pi
