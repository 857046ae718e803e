"""Proxy mode's walk (`nprt.workers.routing.proxy_pairs.walk_queries`: each asked ray against
the boxes of the instances its shard does not hold, and the local-space geometry of every
pair it crosses) through a BVH over those boxes against one flat loop over them, on the
rays of a real render.

A proxy render's K shards run in this process (as in bench_visits) and every walk call is
recorded. The calls are then replayed, alternating BVH and flat, in three timed rounds
after a warm one (numba compiles there): the walk as the shard runs it, pair geometry
included. Every flat replay's pairs are compared with the BVH's (they must be equal). The
shards pick the flat loop up to `toplevel.FLAT_WALK_MAX` remote boxes
(`proxy_query._walk_inputs`); this measures both ways whatever they picked.

    python -m bench.render.bench_proxy_walk                   # forest, city, windy; K 2 8
    python -m bench.render.bench_proxy_walk --scenes /tmp/heldout/foliage.json --ks 8
    python -m bench.render.bench_proxy_walk --smoke
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from bench.common import add_image_flags, add_output_flags, finish, machine, smoke, stored_scene
from bench.render.bench_visits import run
from nprt.workers.kernels.bvh import bvh_build
from nprt.workers.routing import proxy_pairs
from nprt.workers.settings import RenderSettings
from nprt.workers.traversal.toplevel import flat_rows
from nprt.workers.wavefront.inprocess import shards_in_process

ROUNDS = 3  # timed, after one warm round
# Positions in walk_queries' argument list.
BOXES, BVH, COL_OF, MEMBERS, FLAT = 3, 4, 5, 6, 7


def record(scene, s: RenderSettings) -> list[tuple]:
    """Copies of the arguments of every walk call of an in-process render of s."""
    calls = []
    walk = proxy_pairs.walk_queries

    def recorder(*a):
        calls.append(tuple(x.copy() if isinstance(x, np.ndarray) else x for x in a))
        return walk(*a)

    proxy_pairs.walk_queries = recorder
    try:
        run(shards_in_process(scene, s), s)
    finally:
        proxy_pairs.walk_queries = walk
    return calls


def both_ways(call: tuple) -> dict[str, tuple]:
    """The call's arguments with the boxes walked through a BVH over them, and in the flat
    loop. The shards' calls hold the asked boxes alone, as positions 0..k-1."""
    boxes, members = call[BOXES], call[MEMBERS]
    if not np.array_equal(members, np.arange(len(members))):
        raise ValueError("a walk call over a subset of its boxes: not a shard's call")
    k = len(members)
    by_bvh, by_flat = list(call), list(call)
    by_bvh[BVH], by_bvh[COL_OF] = bvh_build(boxes), np.arange(k, dtype=np.int32)
    by_bvh[FLAT] = np.zeros((6, 0))
    by_flat[FLAT] = flat_rows(boxes)
    return {"bvh": tuple(by_bvh), "flat": tuple(by_flat)}


def time_calls(calls: list) -> dict:
    """CPU s of every call through the BVH and flat over ROUNDS rounds, the box counts,
    and whether both give the same pairs."""
    ways = [both_ways(c) for c in calls]
    cpu, same = {"bvh": 0.0, "flat": 0.0}, True
    for rnd in range(ROUNDS + 1):
        for w in ways:
            out = {}
            for name in ("bvh", "flat"):
                t0 = time.process_time()
                out[name] = proxy_pairs.walk_queries(*w[name])
                if rnd:
                    cpu[name] += time.process_time() - t0
            if rnd == 0:
                same &= all(np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
                            for a, b in zip(out["bvh"], out["flat"], strict=True))
    boxes = sorted({len(c[MEMBERS]) for c in calls})
    return {"bvh_s": round(cpu["bvh"], 4), "flat_s": round(cpu["flat"], 4),
            "same": bool(same), "calls": len(calls), "boxes": boxes,
            "rays": int(sum(len(c[0]) for c in calls))}


def bench(args) -> dict:
    rows = []
    for name in args.scenes:
        scene = stored_scene(name, args.size).load()
        for k in args.ks:
            s = RenderSettings(width=args.width, height=args.height, spp=args.spp, seed=0,
                               shards=k, mode="proxy")
            calls = record(scene, s)
            if not calls:
                raise SystemExit(f"{name} K={k}: no proxy walk to time (no shard asks a "
                                 "proxy: every mesh held or replicated)")
            row = {"scene": name, "k": k, **time_calls(calls)}
            rows.append(row)
            print(_line(row), flush=True)
    return {"machine": machine(os.cpu_count()), "settings": vars(args) | {"out": str(args.out)},
            "rounds": ROUNDS, "rows": rows}


def _line(r: dict) -> str:
    return (f"{r['scene']} K={r['k']}: walk BVH {r['bvh_s']:.3f} s, flat {r['flat_s']:.3f} s "
            f"({r['flat_s'] / max(r['bvh_s'], 1e-9):.2f}x), remote boxes "
            f"{', '.join(map(str, r['boxes']))}, {r['rays']:,} rays, same pairs: "
            f"{'yes' if r['same'] else 'NO'}")


def markdown(res: dict) -> str:
    a = res["settings"]
    out = [f"CPU s over {res['rounds']} rounds of every recorded walk call, BVH / flat "
           f"(flat over BVH), a proxy render at {a['width']}x{a['height']}, {a['spp']} spp; "
           "*same*: the flat loop's pairs equal the BVH's.", "",
           "| scene | K | remote boxes | calls | rays walked | BVH s | flat s | flat / BVH | "
           "same |", "|---|---:|---|---:|---:|---:|---:|---:|---|"]
    for r in res["rows"]:
        out.append(f"| {r['scene']} | {r['k']} | {', '.join(map(str, r['boxes']))} | "
                   f"{r['calls']} | {r['rays']:,} | {r['bvh_s']:.3f} | {r['flat_s']:.3f} | "
                   f"{r['flat_s'] / max(r['bvh_s'], 1e-9):.2f}x | "
                   f"{'yes' if r['same'] else 'NO'} |")
    return "\n".join(out) + "\n"


def plot(res: dict, png) -> None:
    """Per scene and K, the walk's CPU through the BVH and flat, side by side."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = res["rows"]
    labels = [f"{r['scene'].split('/')[-1]}\nK = {r['k']}\n{max(r['boxes'])} boxes"
              for r in rows]
    x = np.arange(len(rows))
    fig, ax = plt.subplots(figsize=(max(5, 1.3 * len(rows) + 2), 4))
    ax.bar(x - 0.2, [r["bvh_s"] for r in rows], 0.4, label="BVH")
    ax.bar(x + 0.2, [r["flat_s"] for r in rows], 0.4, label="flat loop")
    ax.set_xticks(x, labels, fontsize=8)
    ax.set_ylabel(f"walk CPU s ({res['rounds']} rounds)")
    ax.set_title("Proxy walk over the remote boxes: BVH against one flat loop")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.render.bench_proxy_walk",
                                 description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    add_image_flags(ap, 320, 180, 8)
    ap.set_defaults(scenes=["forest", "city", "windy"])
    ap.add_argument("--ks", type=int, nargs="+", default=[2, 8])
    add_output_flags(ap)
    # The demo's own size: a tiny scene gets no proxy (the policy replicates its meshes).
    args = smoke(ap.parse_args(argv), scenes=["forest"], width=32, height=24, spp=2, ks=[2])
    res = bench(args)
    if any(not r["same"] for r in res["rows"]):
        raise SystemExit("the flat loop's pairs differ from the BVH's")
    finish(res, args.out / "bench_proxy_walk.json", plot=plot, markdown=markdown,
           update_readme=False)


if __name__ == "__main__":
    main()
