"""Network inputs and depth targets shared by training and inference (numpy only).

"paper": min-max point + (theta/pi, phi/2pi); "xyz": min-max point + (d+1)/2; "line": the ray's
line alone (direction + its closest point to the box centre), depth measured along the line.
"""

from __future__ import annotations

import numpy as np

INPUT_DTYPE = np.float32
N_INPUTS = {"paper": 5, "xyz": 6, "line": 6}
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
    if encoding == "line":
        # Visibility is a property of the line (the query starts outside the geometry), so
        # the line's 4 degrees of freedom are the whole input: no face seams, no phi wrap.
        r = points - 0.5 * (lo + hi)
        q = r - np.sum(r * directions, axis=1, keepdims=True) * directions
        half = np.float32(0.5 * np.linalg.norm(hi - lo))
        return np.concatenate([0.5 + 0.5 * q / half, 0.5 * (directions + 1.0)],
                              axis=1).astype(INPUT_DTYPE)
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


def _along(box: np.ndarray, points: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(n,) float32 line parameter of each point, measured from the closest point to the
    box centre (negative where the ray still approaches the centre)."""
    centre = (0.5 * (box[0] + box[1])).astype(np.float32)
    return np.sum((points - centre) * directions, axis=1)


def depth_target(box, points, directions, t, encoding: str) -> np.ndarray:
    """Depth-net target for hits at distance t (n,) from box points: t / diag, or for
    "line" the hit's line parameter / diag (smooth across the box's edges)."""
    diag = np.float32(np.linalg.norm(box[1] - box[0]))
    y = t + _along(box, points, directions) if encoding == "line" else t
    return (y / diag).astype(np.float32)


def depth_decode(box, points, directions, y, encoding: str) -> np.ndarray:
    """Inverse of depth_target: distance t (n,) float32 from each box point."""
    t = y * np.float32(np.linalg.norm(box[1] - box[0]))
    return t - _along(box, points, directions) if encoding == "line" else t
