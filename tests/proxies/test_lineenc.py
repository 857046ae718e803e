"""The compiled "line" encoding (nprt.proxies.lineenc) gives the bits of the numpy
definition in nprt.proxies.encoding, and a proxy's answers do not change with it."""

from __future__ import annotations

import numpy as np
import pytest

from nprt.proxies.cache import SHIPPED_DIR
from nprt.proxies.encoding import depth_decode, encode, to_proxy_box
from nprt.proxies.inference import Proxy
from nprt.proxies.lineenc import line_depth, line_depth_rows, line_inputs, line_inputs_rows


def _queries(rng, n: int, box: np.ndarray):
    """(n, 3) float32 points and unit directions with the awkward cases mixed in: points on
    the box's planes and at -0.0, NaN points, zero direction components and zero rays."""
    p = rng.uniform(-3, 3, (n, 3)).astype(np.float32)
    d = rng.normal(size=(n, 3))
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    d[::7, 0] = 0.0
    d[::17, 2] = -0.0
    d[::29] = 0.0
    p[::11, 1] = np.float32(box[0, 1])
    p[::13, 2] = np.nan
    p[::19, 0] = -0.0
    return p, d


@pytest.mark.parametrize("seed", range(8))
def test_line_kernels_give_the_numpy_bits(seed):
    rng = np.random.default_rng(seed)
    lo = rng.uniform(-2, 0, 3)
    lo[0] = 0.0 if seed % 2 else lo[0]  # a bound at +0.0 against points at -0.0
    box = np.stack([lo, lo + rng.uniform(0.1, 4, 3)])
    p, d = _queries(rng, 2000, box)
    y = rng.uniform(-1, 2, len(p)).astype(np.float32)

    slid, shift = to_proxy_box(box, p, d)
    x = encode(box, slid, d, "line")
    t = np.maximum(depth_decode(box, slid, d, y, "line") + shift, 0.0)

    lo32, hi32 = box.astype(np.float32)
    x2, slid2, shift2 = line_inputs(lo32, hi32, (0.5 * (lo32 + hi32)).astype(np.float32),
                                    np.float32(0.5 * np.linalg.norm(hi32 - lo32)), p, d)
    t2 = line_depth(np.float32(np.linalg.norm(box[1] - box[0])),
                    (0.5 * (box[0] + box[1])).astype(np.float32), slid, d, y, shift)
    for name, a, b in (("x", x, x2), ("points", slid, slid2), ("shift", shift, shift2),
                       ("t", t, t2)):
        assert a.dtype == b.dtype and a.shape == b.shape, name
        differ = np.flatnonzero(a.view(np.uint32) != b.view(np.uint32))
        assert not len(differ), f"{name} differs at rows/elements {differ[:5]}"


def test_a_shipped_proxy_answers_as_the_numpy_pipeline_does():
    blob = next(f for f in sorted(SHIPPED_DIR.glob("*.nprx")))
    proxy = Proxy.from_bytes(blob.read_bytes())
    assert proxy.meta["encoding"] == "line"
    rng = np.random.default_rng(0)
    p, d = _queries(rng, 3000, proxy.box)
    p = np.nan_to_num(p)  # onnxruntime would pass NaN through; keep the comparison on numbers
    for threshold in (None, float(proxy.meta["threshold"])):
        vis, t = proxy.query(p, d, min_visibility=threshold)
        slid, shift = to_proxy_box(proxy.box, p, d)
        x = encode(proxy.box, slid, d, "line")
        vis0 = proxy.run("visibility", x)
        rows = slice(None) if threshold is None else np.flatnonzero(vis0 >= threshold)
        t0 = np.full(len(p), np.inf, np.float32)
        y = proxy.run("depth", x[rows])
        t0[rows] = np.maximum(depth_decode(proxy.box, slid[rows], d[rows], y, "line")
                              + shift[rows], 0.0)
        assert vis.tobytes() == vis0.tobytes()
        assert t.tobytes() == t0.tobytes()


def test_the_many_proxy_kernels_give_each_proxys_bits():
    """line_inputs_rows / line_depth_rows (several proxies in one call, rows gathered) give
    what line_inputs / line_depth give proxy by proxy."""
    rng = np.random.default_rng(5)
    boxes = [np.stack([lo, lo + rng.uniform(0.1, 4, 3)]) for lo in rng.uniform(-2, 0, (3, 3))]
    lo, hi = (np.array([b[k] for b in boxes], np.float32) for k in (0, 1))
    centre = (0.5 * (lo + hi)).astype(np.float32)
    half = np.array([np.float32(0.5 * np.linalg.norm(b.astype(np.float32)[1]
                                                     - b.astype(np.float32)[0]))
                     for b in boxes])
    scale = np.array([np.float32(np.linalg.norm(b[1] - b[0])) for b in boxes])
    mid = np.array([(0.5 * (b[0] + b[1])).astype(np.float32) for b in boxes])
    p, d = _queries(rng, 900, boxes[0])
    rows = rng.permutation(len(p))[:600].astype(np.int64)
    which = np.sort(rng.integers(0, 3, len(rows)))
    x, slid, shift = line_inputs_rows(lo, hi, centre, half, which, rows, p, d)
    y = rng.uniform(-1, 2, len(rows)).astype(np.float32)
    asked = rng.random(len(rows)) < 0.7
    t = line_depth_rows(scale, mid, which, rows, slid, d, y, shift, asked)
    for g in range(3):
        sel = which == g
        x1, slid1, shift1 = line_inputs(lo[g], hi[g], centre[g], half[g], p[rows[sel]],
                                        d[rows[sel]])
        t1 = line_depth(scale[g], mid[g], slid1, d[rows[sel]], y[sel], shift1)
        t1[~asked[sel]] = np.inf
        for name, a, b in (("x", x1, x[sel]), ("points", slid1, slid[sel]),
                           ("shift", shift1, shift[sel]), ("t", t1, t[sel])):
            assert a.tobytes() == b.tobytes(), (name, g)
