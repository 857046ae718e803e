"""The proxy nets' rows of one query, laid out for onnxruntime in compiled passes: each mesh's
"line" inputs in one block of an even row count (an odd block ends in a zero row, as
`Proxy.run` pads it), the depth net's rows gathered the same way, then each pair's visibility
and t. One pass each replaces a dozen numpy calls a query (a shard asks a few hundred pairs
at a time, so those cost as much as the nets), and no block is copied again to be padded.

Each row is encoded and decoded by the row functions of nprt.proxies.lineenc, in the same
order: the same bits as `line_inputs_rows` / `line_depth_rows` and `Proxy.run`
(tests/workers/test_net_rows.py)."""

from __future__ import annotations

import numpy as np
from numba import njit

from nprt.proxies.lineenc import _depth_row, _inputs_row

JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(**JIT)
def _blocks(start):
    """(meshes + 1,) int64 block starts for blocks of start's sizes, each rounded up to even."""
    nm = len(start) - 1
    at = np.zeros(nm + 1, np.int64)
    for m in range(nm):
        n = start[m + 1] - start[m]
        at[m + 1] = at[m] + n + (n & 1)
    return at


@njit(**JIT)
def net_inputs(lo, hi, centre, half, start, grouped, point, qdir):
    """The visibility net's input of every asked pair. lo, hi, centre (meshes, 3) float32 and
    half (meshes,) float32: each mesh's box constants (`Proxy.line_constants`); mesh m's pairs
    are grouped[start[m]:start[m + 1]] (start (meshes + 1,) int64, grouped (a,) int64 pair
    rows); point, qdir (p, 3) float32 each pair's local query. Returns x (R, 6) float32, mesh
    m's rows at x[at[m]:at[m + 1]] (an odd count followed by a zero row), on_box (R, 3) and
    shift (R,) float32 (`lineenc.line_inputs`' p and shift), at (meshes + 1,) int64."""
    at = _blocks(start)
    size = at[-1]
    x = np.zeros((size, 6), np.float32)
    on_box = np.zeros((size, 3), np.float32)
    shift = np.zeros(size, np.float32)
    c = np.empty(3, np.float32)
    for m in range(len(start) - 1):
        for i in range(start[m], start[m + 1]):
            q = grouped[i]
            _inputs_row(lo[m], hi[m], centre[m], half[m], point[q], qdir[q], x, on_box, shift,
                        at[m] + i - start[m], c)
    return x, on_box, shift, at


@njit(**JIT)
def deep_inputs(v, thr_q, cut, mesh, start, grouped, at, x):
    """The depth net's rows: those of x whose visibility v (R,) float32 reaches their pair's
    threshold (thr_q (q, meshes) float32 row j for the pairs cut[j]:cut[j + 1] of query j;
    mesh (p,) int64 each pair's mesh), mesh by mesh in the same order, each mesh's block
    padded to even as in `net_inputs`. Returns x_deep (D, 6) float32, mesh m's at
    x_deep[dat[m]:dat[m + 1]], dat (meshes + 1,) int64 and deep (R,) int64 each row's place
    in x_deep (-1: none)."""
    nm = len(start) - 1
    deep = np.full(len(v), -1, np.int64)
    count = np.zeros(nm + 1, np.int64)
    for m in range(nm):
        for i in range(start[m], start[m + 1]):
            r = at[m] + i - start[m]
            q = grouped[i]
            j = 0
            while q >= cut[j + 1]:
                j += 1
            if v[r] >= thr_q[j, mesh[q]]:
                deep[r] = count[m + 1]
                count[m + 1] += 1
    dat = _blocks(count.cumsum())
    x_deep = np.zeros((dat[-1], x.shape[1]), np.float32)
    for m in range(nm):
        for r in range(at[m], at[m] + start[m + 1] - start[m]):
            if deep[r] >= 0:
                deep[r] += dat[m]
                x_deep[deep[r]] = x[r]
    return x_deep, dat, deep


@njit(**JIT)
def net_answers(p, start, grouped, at, v, deep, y, on_box, shift, qdir, scale, dcentre):
    """Per pair (p of them): vis (p,) float32 the visibility (0 where not asked) and tp (p,)
    float32 the proxy's t in local units (`lineenc.line_depth` of the depth net's y at the
    row's place deep, inf where not asked or below the threshold). scale (meshes,) and
    dcentre (meshes, 3) float32: each mesh's depth constants; the rest as `deep_inputs`."""
    vis = np.zeros(p, np.float32)
    tp = np.full(p, np.inf, np.float32)
    for m in range(len(start) - 1):
        for i in range(start[m], start[m + 1]):
            q = grouped[i]
            r = at[m] + i - start[m]
            vis[q] = v[r]
            if deep[r] >= 0:
                tp[q] = _depth_row(scale[m], dcentre[m], on_box[r], qdir[q], y[deep[r]],
                                   shift[r])
    return vis, tp
