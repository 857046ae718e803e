"""The exact policy's routing search (`nprt.workers.kernels.nearest.near_search`: the nearest
box on a shard a ray has not visited, before its closest hit here) through the instance
BVH against one flat loop over the candidates' slabs, on the rays of a real render.

An exact render's K shards run in this process (as in bench_visits) and every call of the
two walking kernels (`crossings.closest_walk`, `crossings.occluded_walk`, which trace a
ray's local boxes and then search its next stop) is recorded. The calls are then replayed,
alternating BVH and flat, in three timed rounds after a warm one:
- *search*: the search alone (`nearest_owner`) on the closest walks' rays, cut where the
  walk cut them, with the candidates the shard had, and again with every box a candidate
  (where the flat loop stops winning: `toplevel.ROUTE_FLAT_MAX`);
- *walks*: the whole walking kernels, tracing included, as the shard calls them.
Every replay's answers are compared with the BVH's (they must be equal).

    python -m bench.render.bench_route_search                   # forest, city; K = 2
    python -m bench.render.bench_route_search --scenes city --ks 2 4
    python -m bench.render.bench_route_search --smoke
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from bench.common import add_image_flags, add_output_flags, finish, machine, smoke, stored_scene
from bench.render.bench_visits import run
from nprt.workers.kernels import crossings
from nprt.workers.kernels.nearest import nearest_owner
from nprt.workers.settings import RenderSettings
from nprt.workers.traversal import local
from nprt.workers.traversal.toplevel import flat_rows
from nprt.workers.wavefront.inprocess import shards_in_process

# Positions in the walking kernels' argument lists (crossings.closest_walk / occluded_walk).
CLOSEST = {"origin": 1, "direction": 2, "slack": 4, "boxes": 6, "bvh": slice(11, 16),
           "route": 25, "cand_owner": 26, "cands": 27, "cand_flat": 28, "cand_bvh": 29,
           "visited": 30, "near_t": 31, "near_owner": 32, "near_tmax": 33}
OCCLUDED = {"route": 20, "cand_bvh": 24, "near_t": 26, "near_owner": 27, "occluded": 19}
ROUNDS = 3  # timed, after one warm round (numba compiles there)


def record(scene, s: RenderSettings) -> tuple[dict, list]:
    """({"closest": [args], "occluded": [args]}, the shards): copies of every routed walk
    call of an in-process render of s (the calls' outputs are overwritten on replay, so
    copied). The calls hold the shards' Embree scenes by address: keep the shards alive
    while they are replayed."""
    calls = {"closest": [], "occluded": []}
    kernels = {"closest": crossings.closest_walk, "occluded": crossings.occluded_walk}

    def recorder(name):
        def call(*a):
            calls[name].append(tuple(x.copy() if isinstance(x, np.ndarray) else x for x in a))
            return kernels[name](*a)
        return call

    shards = shards_in_process(scene, s)
    local.crossings.closest_walk = recorder("closest")
    local.crossings.occluded_walk = recorder("occluded")
    try:
        run(shards, s)
    finally:
        local.crossings.closest_walk = kernels["closest"]
        local.crossings.occluded_walk = kernels["occluded"]
    return {n: [c for c in v if c[(CLOSEST if n == "closest" else OCCLUDED)["route"]]]
            for n, v in calls.items()}, shards


def _every_box(c) -> tuple:
    """(cand_owner, cands, cand_flat, visited) with every box a candidate on shard 1."""
    boxes, n = c[CLOSEST["boxes"]], len(c[CLOSEST["origin"]])
    m = boxes.shape[0]
    return (np.ones(m, np.int32), np.arange(m, dtype=np.int64),
            flat_rows(boxes), np.zeros(n, np.uint64))


def time_search(calls: list, every: bool) -> dict:
    """The search alone on the closest walks' rays: CPU s through the BVH and flat, the
    candidates per call, and whether the answers agree."""
    cpu, same, cands = {True: 0.0, False: 0.0}, True, set()
    for rnd in range(ROUNDS + 1):
        for c in calls:
            owner, ids, flat, visited = (_every_box(c) if every else
                                         (c[CLOSEST["cand_owner"]], c[CLOSEST["cands"]],
                                          c[CLOSEST["cand_flat"]], c[CLOSEST["visited"]]))
            cands.add(len(ids))
            lim = c[CLOSEST["near_tmax"]].astype(np.float64) * (1.0 + c[CLOSEST["slack"]])
            got = []
            for use_bvh in (True, False):
                t0 = time.process_time()
                got.append(nearest_owner(c[CLOSEST["origin"]], c[CLOSEST["direction"]], lim,
                                         c[CLOSEST["boxes"]], *c[CLOSEST["bvh"]], owner, ids,
                                         flat, use_bvh, visited))
                if rnd:
                    cpu[use_bvh] += time.process_time() - t0
            same &= np.array_equal(*got)
    return {"bvh_s": round(cpu[True], 4), "flat_s": round(cpu[False], 4),
            "candidates": sorted(cands), "same": bool(same)}


def time_walks(calls: list, name: str) -> dict:
    """The whole walking kernel, tracing included: CPU s with the recorded search through
    the BVH and through the flat loop, and whether every output agrees."""
    at = CLOSEST if name == "closest" else OCCLUDED
    kernel = crossings.closest_walk if name == "closest" else crossings.occluded_walk
    cpu, same = {True: 0.0, False: 0.0}, True
    for rnd in range(ROUNDS + 1):
        for c in calls:
            outs = []
            for use_bvh in (True, False):
                args = [x.copy() if isinstance(x, np.ndarray) else x for x in c]
                args[at["cand_bvh"]] = use_bvh
                t0 = time.process_time()
                kernel(*args)
                if rnd:
                    cpu[use_bvh] += time.process_time() - t0
                outs.append([a for a in args if isinstance(a, np.ndarray)])
            same &= all(np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
                        for a, b in zip(*outs, strict=True))
    return {"bvh_s": round(cpu[True], 4), "flat_s": round(cpu[False], 4), "same": bool(same),
            "calls": len(calls), "rays": int(sum(len(c[1]) for c in calls))}


def bench(args) -> dict:
    rows = []
    for name in args.scenes:
        scene = stored_scene(name, args.size).load()
        for k in args.ks:
            s = RenderSettings(width=args.width, height=args.height, spp=args.spp, seed=0,
                               shards=k, mode="exact")
            calls, shards = record(scene, s)
            if not calls["closest"] or not len(calls["closest"][0][15]):  # prim: no BVH
                raise SystemExit(f"{name}: no routed walk over an instance BVH to compare "
                                 "(too few instances, or K = 1)")
            row = {"scene": name, "k": k,
                   "search": time_search(calls["closest"], every=False),
                   "search_every_box": time_search(calls["closest"], every=True),
                   "closest_walk": time_walks(calls["closest"], "closest"),
                   "occluded_walk": time_walks(calls["occluded"], "occluded")}
            del shards  # their Embree scenes: no call replays them now
            rows.append(row)
            print(_line(row), flush=True)
    return {"machine": machine(os.cpu_count()), "settings": vars(args) | {"out": str(args.out)},
            "rounds": ROUNDS, "rows": rows}


def _pair(x: dict) -> str:
    return f"{x['bvh_s']:.3f} / {x['flat_s']:.3f} ({x['flat_s'] / max(x['bvh_s'], 1e-9):.2f}x)"


def _line(r: dict) -> str:
    return (f"{r['scene']} K={r['k']}: search {_pair(r['search'])}, every box "
            f"{_pair(r['search_every_box'])}, closest walk {_pair(r['closest_walk'])}, "
            f"occluded walk {_pair(r['occluded_walk'])}")


def markdown(res: dict) -> str:
    a = res["settings"]
    head = (f"CPU s over {res['rounds']} rounds, BVH / flat (flat over BVH), an exact render "
            f"at {a['width']}x{a['height']}, {a['spp']} spp, default size; *same*: every "
            "answer of the flat loop equals the BVH's.\n\n"
            "| scene | K | candidates | search | every box a candidate | closest walk | "
            "occluded walk | rays (closest / occluded) | same |\n"
            "|---|---:|---|---|---|---|---|---|---|\n")
    rows = []
    for r in res["rows"]:
        parts = (r["search"], r["search_every_box"], r["closest_walk"], r["occluded_walk"])
        rows.append(
            f"| {r['scene']} | {r['k']} | {', '.join(map(str, r['search']['candidates']))} "
            f"(all: {r['search_every_box']['candidates'][0]}) | "
            + " | ".join(_pair(x) for x in parts)
            + f" | {r['closest_walk']['rays']:,} / {r['occluded_walk']['rays']:,} | "
            f"{'yes' if all(x['same'] for x in parts) else 'NO'} |")
    return head + "\n".join(rows)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.render.bench_route_search",
                                 description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    add_image_flags(ap, 320, 180, 8)
    ap.add_argument("--ks", type=int, nargs="+", default=[2])
    add_output_flags(ap)
    args = smoke(ap.parse_args(argv), scenes=["forest"], size="tiny", width=24, height=16,
                 spp=1, ks=[2])
    res = bench(args)
    finish(res, args.out / "bench_route_search.json", markdown=markdown,
           section="bench_route_search", update_readme=not args.no_readme,
           intro="`python -m bench.render.bench_route_search` (`{json}`):\n\n")


if __name__ == "__main__":
    main()
