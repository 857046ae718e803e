"""Compiled twins of nprt.proxies.encoding for the "line" encoding at render time: the slide
to the proxy box, the net input and the depth decoding in one pass over the rows each,
where numpy makes a dozen passes and temporaries per call (a shard asks a proxy about a
few hundred rows at a time, so numpy's per-call cost was as large as the nets').

They give the same float32 bits as the numpy functions, which stay the definition (training
uses them): the same operations in the same order, in float32, with numpy's NaN rules
(tests/proxies/test_lineenc.py compares them row for row, NaN and zero directions too).
Imported when a proxy first answers, never by the driver (numba)."""

from __future__ import annotations

import numpy as np
from numba import njit

JIT = {"cache": True, "nogil": True, "error_model": "numpy"}
_HALF = np.float32(0.5)
_ONE = np.float32(1.0)
_ZERO = np.float32(0.0)


@njit(inline="always")
def _fmin(a, b):  # np.fmin: the number when one side is NaN
    return b if a != a else (a if b != b else (a if a <= b else b))


@njit(inline="always")
def _fmax(a, b):  # np.fmax
    return b if a != a else (a if b != b else (a if a >= b else b))


@njit(inline="always")
def _clip(v, lo, hi):  # np.clip: NaN stays NaN; a tie (+0 against -0 too) gives the bound
    if v != v:
        return v
    x = v if v > lo else lo
    return x if x < hi else hi


@njit(**JIT)
def line_inputs(lo, hi, centre, half, points, directions):
    """lo, hi, centre (3,) float32 (centre = 0.5 * (lo + hi) in float32), half float32;
    points, directions (n, 3) float32. Returns x (n, 6) float32 net inputs, p (n, 3) float32
    points on the proxy box and shift (n,) float32 (encoding.to_proxy_box + encode)."""
    n = points.shape[0]
    x = np.empty((n, 6), np.float32)
    p = np.empty((n, 3), np.float32)
    shift = np.empty(n, np.float32)
    c = np.empty(3, np.float32)
    for i in range(n):
        s = np.float32(np.nan)
        for a in range(3):
            c[a] = _clip(points[i, a], lo[a], hi[a])
            t0 = (lo[a] - c[a]) / directions[i, a]
            t1 = (hi[a] - c[a]) / directions[i, a]
            s = _fmin(t0, t1) if a == 0 else _fmax(s, _fmin(t0, t1))
        # np.minimum(s, 0.0) then nan_to_num: NaN, -inf and anything not below 0 (-0.0
        # too: np.minimum gives its second zero) become +0.
        if not (-np.inf < s < _ZERO):
            s = _ZERO
        shift[i] = s
        dot = _ZERO
        for a in range(3):
            p[i, a] = c[a] + s * directions[i, a]
            r = p[i, a] - centre[a]
            dot = r * directions[i, a] if a == 0 else dot + r * directions[i, a]
        for a in range(3):
            q = (p[i, a] - centre[a]) - dot * directions[i, a]
            x[i, a] = _HALF + _HALF * q / half
            x[i, 3 + a] = _HALF * (directions[i, a] + _ONE)
    return x, p, shift


@njit(**JIT)
def line_depth(scale, centre, points, directions, y, shift):
    """encoding.depth_decode for "line", then Proxy.query's max(t + shift, 0): scale float32
    (the proxy box's diagonal), centre (3,) float32, points / directions (n, 3) float32,
    y (n,) float32 depth-net outputs, shift (n,) float32. Returns t (n,) float32."""
    n = points.shape[0]
    t = np.empty(n, np.float32)
    for i in range(n):
        along = _ZERO
        for a in range(3):
            v = (points[i, a] - centre[a]) * directions[i, a]
            along = v if a == 0 else along + v
        d = (y[i] * scale - along) + shift[i]
        t[i] = d if (d != d or d > _ZERO) else _ZERO  # np.maximum(d, 0.0): NaN stays
    return t
