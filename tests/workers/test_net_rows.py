"""The proxy nets' rows laid out in compiled passes (nprt.workers.routing.net_rows, with
Proxy.run_even) give the bits of the per-mesh path they replaced: lineenc's row functions and
Proxy.run on each mesh's rows, with odd blocks, meshes without rows and a block longer than
one onnxruntime call."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nprt.proxies.inference import Proxy
from nprt.proxies.lineenc import line_depth_rows, line_inputs_rows
from nprt.workers.routing import net_rows

SHIPPED = Path(__file__).resolve().parents[2] / "proxies" / "shipped"


@pytest.fixture(scope="module")
def proxies() -> list[Proxy]:
    """Three shipped "line" proxies of different meshes."""
    got, meshes = [], set()
    for path in sorted(SHIPPED.glob("*.nprx")):
        p = Proxy.from_bytes(path.read_bytes())
        if p.meta["encoding"] == "line" and p.meta["content_hash"] not in meshes:
            meshes.add(p.meta["content_hash"])
            got.append(p)
        if len(got) == 3:
            return got
    pytest.skip("fewer than three shipped line proxies")


def _before(proxies, start, grouped, point, qdir, thr):
    """The per-mesh path (proxy_query._ask_nets before net_rows): vis, tp per pair."""
    consts = [np.stack(c) for c in zip(*(p.line_constants() for p in proxies), strict=True)]
    lo, hi, centre, half, scale, dcentre = consts
    which = np.repeat(np.arange(len(start) - 1), np.diff(start))
    x, on_box, shift = line_inputs_rows(lo, hi, centre, half, which, grouped, point, qdir)
    v = np.empty(len(grouped), np.float32)
    for m in np.flatnonzero(np.diff(start)):
        v[start[m]:start[m + 1]] = proxies[m].run("visibility", x[start[m]:start[m + 1]])
    deep = v >= thr[grouped]
    at = np.r_[0, np.cumsum(deep)][start]
    y_deep = np.empty(int(deep.sum()), np.float32)
    for m in range(len(proxies)):
        if at[m + 1] > at[m]:
            y_deep[at[m]:at[m + 1]] = proxies[m].run("depth", x[deep][at[m]:at[m + 1]])
    y = np.zeros(len(grouped), np.float32)
    y[deep] = y_deep
    vis = np.zeros(len(point), np.float32)
    tp = np.full(len(point), np.inf, np.float32)
    vis[grouped] = v
    tp[grouped] = line_depth_rows(scale, dcentre, which, grouped, on_box, qdir, y, shift, deep)
    return vis, tp, consts


@pytest.mark.parametrize("sizes", [(7, 0, 12), (1, 4097, 3), (0, 0, 31)])
def test_net_rows_give_the_bits_of_the_per_mesh_path(proxies, sizes):
    rng = np.random.default_rng(sum(sizes))
    p = sum(sizes) + 50  # pairs not asked about too
    point = rng.uniform(-1.2, 1.2, (p, 3)).astype(np.float32)
    qdir = rng.normal(size=(p, 3))
    qdir = (qdir / np.linalg.norm(qdir, axis=1, keepdims=True)).astype(np.float32)
    qdir[::11, 1] = 0.0
    grouped = rng.permutation(p)[:sum(sizes)].astype(np.int64)
    start = np.r_[0, np.cumsum(sizes)].astype(np.int64)
    mesh = np.zeros(p, np.int64)  # pairs not asked about keep mesh 0
    for m in range(3):
        mesh[grouped[start[m]:start[m + 1]]] = m
    cut = np.array([0, p // 3, p], np.int64)  # two queries, each its thresholds
    thr_q = rng.choice([0.3, 0.5, 0.7], (2, 3)).astype(np.float32)
    thr = thr_q[(np.arange(p) >= cut[1]).astype(int), mesh]
    want_vis, want_tp, consts = _before(proxies, start, grouped, point, qdir, thr)
    lo, hi, centre, half, scale, dcentre = consts

    x, on_box, shift, at = net_rows.net_inputs(lo, hi, centre, half, start, grouped, point,
                                               qdir)
    assert (np.diff(at) % 2 == 0).all() and (np.diff(at) - np.diff(start) <= 1).all()
    v = np.empty(len(x), np.float32)
    for m in np.flatnonzero(np.diff(at)):
        v[at[m]:at[m + 1]] = proxies[m].run_even("visibility", x[at[m]:at[m + 1]])
    x_deep, dat, deep = net_rows.deep_inputs(v, thr_q, cut, mesh, start, grouped, at, x)
    assert (np.diff(dat) % 2 == 0).all()
    y = np.empty(len(x_deep), np.float32)
    for m in np.flatnonzero(np.diff(dat)):
        y[dat[m]:dat[m + 1]] = proxies[m].run_even("depth", x_deep[dat[m]:dat[m + 1]])
    vis, tp = net_rows.net_answers(p, start, grouped, at, v, deep, y, on_box, shift, qdir,
                                   scale, dcentre)
    assert np.isfinite(want_tp).any() and (want_vis[grouped] < thr[grouped]).any()
    assert vis.tobytes() == want_vis.tobytes()
    assert tp.tobytes() == want_tp.tobytes()


def test_run_even_refuses_an_odd_row_count(proxies):
    with pytest.raises(ValueError, match="even number of rows, got 3"):
        proxies[0].run_even("visibility", np.zeros((3, 6), np.float32))
