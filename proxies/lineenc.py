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


@njit(inline="always")
def _inputs_row(lo, hi, centre, half, pt, dr, x, p, shift, i, c):
    """One row of line_inputs: pt, dr (3,) float32 views of the query; writes row i of x, p,
    shift (c (3,) float32 scratch)."""
    s = np.float32(np.nan)
    for a in range(3):
        c[a] = _clip(pt[a], lo[a], hi[a])
        t0 = (lo[a] - c[a]) / dr[a]
        t1 = (hi[a] - c[a]) / dr[a]
        s = _fmin(t0, t1) if a == 0 else _fmax(s, _fmin(t0, t1))
    # np.minimum(s, 0.0) then nan_to_num: NaN, -inf and anything not below 0 (-0.0
    # too: np.minimum gives its second zero) become +0.
    if not (-np.inf < s < _ZERO):
        s = _ZERO
    shift[i] = s
    dot = _ZERO
    for a in range(3):
        p[i, a] = c[a] + s * dr[a]
        r = p[i, a] - centre[a]
        dot = r * dr[a] if a == 0 else dot + r * dr[a]
    for a in range(3):
        q = (p[i, a] - centre[a]) - dot * dr[a]
        x[i, a] = _HALF + _HALF * q / half
        x[i, 3 + a] = _HALF * (dr[a] + _ONE)


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
        _inputs_row(lo, hi, centre, half, points[i], directions[i], x, p, shift, i, c)
    return x, p, shift


@njit(**JIT)
def line_inputs_rows(lo, hi, centre, half, which, rows, points, directions):
    """line_inputs for several proxies at once: lo, hi, centre (g, 3) float32 and half (g,)
    float32 per proxy; which (r,) int64 the proxy of each output row, rows (r,) int64 the
    row of points, directions (n, 3) float32 it encodes. Returns x (r, 6), p (r, 3) and
    shift (r,) float32, row i as line_inputs gives it for points[rows[i]]."""
    r = len(rows)
    x = np.empty((r, 6), np.float32)
    p = np.empty((r, 3), np.float32)
    shift = np.empty(r, np.float32)
    c = np.empty(3, np.float32)
    for i in range(r):
        g = which[i]
        _inputs_row(lo[g], hi[g], centre[g], half[g], points[rows[i]], directions[rows[i]],
                    x, p, shift, i, c)
    return x, p, shift


@njit(inline="always")
def _depth_row(scale, centre, pt, dr, y, shift):
    along = _ZERO
    for a in range(3):
        v = (pt[a] - centre[a]) * dr[a]
        along = v if a == 0 else along + v
    d = (y * scale - along) + shift
    return d if (d != d or d > _ZERO) else _ZERO  # np.maximum(d, 0.0): NaN stays


@njit(**JIT)
def line_depth(scale, centre, points, directions, y, shift):
    """encoding.depth_decode for "line", then Proxy.query's max(t + shift, 0): scale float32
    (the proxy box's diagonal), centre (3,) float32, points / directions (n, 3) float32,
    y (n,) float32 depth-net outputs, shift (n,) float32. Returns t (n,) float32."""
    n = points.shape[0]
    t = np.empty(n, np.float32)
    for i in range(n):
        t[i] = _depth_row(scale, centre, points[i], directions[i], y[i], shift[i])
    return t


@njit(**JIT)
def line_depth_rows(scale, centre, which, rows, points, directions, y, shift, asked):
    """line_depth for several proxies at once: scale (g,) float32 and centre (g, 3) float32
    per proxy; which (r,) int64 the proxy of each row; points (r, 3) float32 (line_inputs'
    p); directions (n, 3) float32 read at rows (r,) int64; y, shift (r,) float32; asked (r,)
    bool (the depth net ran). Returns t (r,) float32, inf where not asked."""
    r = len(which)
    t = np.full(r, np.inf, np.float32)
    for i in range(r):
        if asked[i]:
            g = which[i]
            t[i] = _depth_row(scale[g], centre[g], points[i], directions[rows[i]], y[i],
                              shift[i])
    return t
