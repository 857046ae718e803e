"""Smaller boxes: one proxy per cell of a k-d split of the mesh, against one proxy per mesh,
scored on the same held-out mesh-level rays (issue 11, "what lifts accuracy").

A mesh's triangles are split at the median centroid along the longest axis, `levels` times
(2^levels cells, each with the tight box of its own triangles). A mesh-level query (point on
the mesh's proxy box, direction) enters every cell box it crosses; each cell's proxy answers
from its own entry point, and the mesh-level answer is a hit iff any cell predicts one, at
the nearest predicted distance. The step budget is split evenly over the cells, so each
row costs the same optimiser steps as the single proxy.

    python -m bench.experiments.bench_proxy_cells [--mesh forest:default:pine] [--levels 0 1 2 3]

Appends one row per mesh, width and level count to bench/results/proxy_cells.jsonl.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from bench.common import RESULTS, smoke


def split_cells(mesh, levels: int):
    """2^levels sub-meshes by median split of triangle centroids on the longest axis."""
    from nprt.scene.model import Mesh

    v = mesh.vertices.astype(np.float64)
    groups = [np.arange(len(mesh.faces))]
    for _ in range(levels):
        nxt = []
        for g in groups:
            c = v[mesh.faces[g]].mean(axis=1)  # (m, 3) centroids
            axis = int(np.argmax(c.max(0) - c.min(0)))
            order = np.argsort(c[:, axis], kind="stable")
            half = len(g) // 2
            nxt += [g[order[:half]], g[order[half:]]]
        groups = nxt
    cells = []
    for i, g in enumerate(groups):
        used, faces = np.unique(mesh.faces[g], return_inverse=True)
        cells.append(Mesh(f"{mesh.name}.c{i}", mesh.vertices[used],
                          faces.reshape(-1, 3).astype(np.uint32)))
    return cells


def composed_query(proxies, points, directions):
    """Mesh-level prediction from cell proxies: (hit (n,) bool, t (n,) float32)."""
    n = len(points)
    hit, t = np.zeros(n, bool), np.full(n, np.inf, np.float32)
    p64, d64 = points.astype(np.float64), directions.astype(np.float64)
    for proxy in proxies:
        lo, hi = proxy.box
        with np.errstate(divide="ignore", invalid="ignore"):
            t0, t1 = (lo - p64) / d64, (hi - p64) / d64
        t_in = np.maximum(np.fmax.reduce(np.fmin(t0, t1), axis=1), 0.0)
        t_out = np.fmin.reduce(np.fmax(t0, t1), axis=1)
        rows = np.flatnonzero(t_out > t_in)
        if not len(rows):
            continue
        entry = (p64[rows] + t_in[rows, None] * d64[rows]).astype(np.float32)
        vis, tc = proxy.query(entry, directions[rows])
        ok = vis >= proxy.meta["threshold"]
        r, tt = rows[ok], (t_in[rows] + tc)[ok].astype(np.float32)
        hit[r] = True
        t[r] = np.minimum(t[r], tt)
    return hit, t


def run_one(mesh, levels: int, width: int, steps: int, samples: int, eval_n: int) -> dict:
    from nprt.proxies.config import EVAL_SEED_OFFSET, ProxyConfig
    from nprt.proxies.sampling import sample_rays
    from nprt.proxies.train import train_proxy
    from nprt.workers.traversal.geometry import MeshGeometry

    cells = split_cells(mesh, levels) if levels else [mesh]
    base = ProxyConfig(width=width, steps=max(2, steps // len(cells)),
                       n_samples=max(1 << 14, samples // len(cells)))
    c0, t0 = time.process_time(), time.perf_counter()
    proxies = [train_proxy(c, base, progress=False) for c in cells]
    cpu = time.process_time() - c0
    geo = MeshGeometry(mesh)
    held = sample_rays(mesh, eval_n, base.seed + EVAL_SEED_OFFSET, base.grid, geo)
    pred, t = composed_query(proxies, held.points, held.directions)
    both = pred & held.hit & np.isfinite(t)
    diag = float(np.linalg.norm(np.subtract(*mesh.bounds[::-1])))
    return {"mesh": mesh.name, "triangles": len(mesh.faces), "levels": levels,
            "cells": len(cells), "width": width, "steps_total": base.steps * len(cells),
            "samples_total": base.n_samples * len(cells),
            "accuracy": float((pred == held.hit).mean()),
            "fp_rate": float((pred & ~held.hit).sum() / max(1, (~held.hit).sum())),
            "fn_rate": float((~pred & held.hit).sum() / max(1, held.hit.sum())),
            "depth_err_rel": float(np.abs(t - held.t)[both].mean() / diag) if both.any() else 0,
            "cell_accuracy": [p.meta["report"]["accuracy"] for p in proxies],
            "proxy_bytes": int(sum(p.nbytes for p in proxies)),
            "train_cpu_s": cpu, "wall_s": time.perf_counter() - t0,
            "load": os.getloadavg()[0]}


def find_mesh(spec: str):
    """'forest:default:pine' (a demo mesh) or 'family:small:sparse_foliage'."""
    from bench.common import bench_scene

    scene, size, name = spec.split(":")
    return next(m for m in bench_scene(scene, size).meshes if m.name == name)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mesh", nargs="+", default=["forest:default:pine"])
    ap.add_argument("--levels", type=int, nargs="+", default=[0, 1, 2, 3])
    ap.add_argument("--width", type=int, nargs="+", default=[32])
    ap.add_argument("--steps", type=int, default=12000, help="optimiser steps, all cells")
    ap.add_argument("--samples", type=int, default=1 << 19, help="training rays, all cells")
    ap.add_argument("--eval", type=int, default=1 << 16)
    ap.add_argument("--smoke", action="store_true",
                    help="a tiny pine, 0 and 1 levels, 20 steps, for the CI smoke test")
    args = smoke(ap.parse_args(argv), mesh=["forest:tiny:pine"], levels=[0, 1], steps=20,
                 samples=1 << 12, eval=1 << 12)
    RESULTS.mkdir(exist_ok=True)
    out = RESULTS / "proxy_cells.jsonl"
    for spec in args.mesh:
        mesh = find_mesh(spec)
        for width in args.width:
            for levels in args.levels:
                row = run_one(mesh, levels, width, args.steps, args.samples, args.eval)
                row["spec"] = spec
                print(json.dumps(row), flush=True)
                with out.open("a") as f:
                    f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
