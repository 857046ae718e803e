"""Network input encoding shared by training and inference (numpy only): min-max point on
the proxy box plus direction angles, and moving a caller's box point onto the proxy box."""

from __future__ import annotations

import numpy as np

INPUT_DTYPE = np.float32
N_INPUTS = {"paper": 5, "xyz": 6}
_TWO_PI = np.float32(2 * np.pi)


def to_proxy_box(box: np.ndarray, points: np.ndarray, directions: np.ndarray):
    """Slide each query back along its ray to where it enters the proxy box.

    Callers give points on the mesh AABB (or on a slightly padded copy of it); the proxy
    was trained on points of its own padded box, so entry points there are what it knows.
    box : (2, 3) float64; points, directions : (n, 3) float32, directions into the box
    returns points (n, 3) float32 on the proxy box, shift (n,) float32 <= 0: the signed
    distance moved, to be added to the predicted t
    """
    lo, hi = box.astype(np.float32)
    p = np.clip(points, lo, hi)
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (lo - p) / directions
        t1 = (hi - p) / directions
    # fmax/fmin skip the NaN of 0/0 (a point on a slab plane with a zero direction component).
    shift = np.fmax.reduce(np.fmin(t0, t1), axis=1)  # (n,) entry parameter, <= 0
    shift = np.nan_to_num(np.minimum(shift, 0.0), nan=0.0, neginf=0.0).astype(INPUT_DTYPE)
    return (p + shift[:, None] * directions).astype(INPUT_DTYPE), shift


def encode(box: np.ndarray, points: np.ndarray, directions: np.ndarray, encoding: str):
    """Network input for queries already on the proxy box.

    box : (2, 3) float64; points : (n, 3) float32; directions : (n, 3) float32 unit
    returns (n, N_INPUTS[encoding]) float32
    """
    lo, hi = box.astype(np.float32)
    p01 = np.clip((points - lo) / (hi - lo), 0.0, 1.0)
    if encoding == "xyz":
        return np.concatenate([p01, 0.5 * (directions + 1.0)], axis=1).astype(INPUT_DTYPE)
    if encoding != "paper":
        raise ValueError(f"unknown encoding {encoding!r}")
    x = np.empty((len(points), 5), INPUT_DTYPE)
    x[:, :3] = p01
    x[:, 3] = np.arccos(np.clip(directions[:, 2], -1.0, 1.0)) / np.float32(np.pi)
    x[:, 4] = np.mod(np.arctan2(directions[:, 1], directions[:, 0]), _TWO_PI) / _TWO_PI
    return x
