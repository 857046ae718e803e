"""How long a shard waits to merge parcels into one step (nprt.workers.runtime.remote,
HOLD_RAYS and HOLD_S), how long a small parcel waits for more before it leaves (SEND_RAYS
and SEND_S, nprt.workers.runtime.outbox), how many rays leaving make a step send before it
ends (EMIT_RAYS), up to how many rays left after an iteration go on in the next step once
parcels wait (CARRY_RAYS), how many passes are live at once (the coordinator's window), and whether
finished passes' films ride on the shards' next polls or are collected at once
(coordinator.COLLECT_ON_POLL_FROM_K), side by side in one run: the 1-core reference, then each
scene at one K in exact and proxy mode with each combination of settings.

A step pays a fixed cost (a Ray call per target, the per-step glue) and a cost per ray. A
shard whose inbox holds few rays can step at once (small steps: more fixed cost per ray) or
wait a little for more (fewer, bigger steps, but the wait can leave its core idle). Per
row: render wall and CPU against the reference's, steps, parcels, rays per parcel, Ray's
threads (shard CPU outside the wavefront thread), the busy fraction, and whether the film
equals the first (baseline) hold's film: it must, films never depend on step grouping.

Meaningful on a machine with a core per shard and one for the coordinator: on fewer cores
the shards wait for CPU anyway, and their steps are big whatever the hold.

    python -m bench.render.bench_step_hold --scenes city forest --k 8
    python -m bench.render.bench_step_hold --scenes city --k 4 --holds 0:0 16384:8 --rounds 2
    python -m bench.render.bench_step_hold --scenes city --holds 16384:8 --sends 0:0 1024:20
    python -m bench.render.bench_step_hold --k 2 --holds 16384:8 --windows 12 48 --rounds 2
    python -m bench.render.bench_step_hold --k 2 --holds 16384:8 --emits 0 8192 --rounds 2
    python -m bench.render.bench_step_hold --holds 16384:8 --collects now poll --rounds 3
    python -m bench.render.bench_step_hold --k 4 --holds 16384:8 --carries 0 1048576 --rounds 2
    python -m bench.render.bench_step_hold --smoke
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from bench.common import (
    add_output_flags,
    finish,
    fmt_or_blank,
    machine,
    raylet_cpu_s,
    smoke,
    stored_scene,
    window_arg,
)
from bench.render.bench_strong_scaling import run_one
from nprt.workers.runtime import coordinator, remote
from nprt.workers.settings import RenderSettings

HOLDS = ["0:0", "8192:2", "8192:4", "16384:8"]  # rays:milliseconds; the first is the baseline
SENDS = [f"{remote.SEND_RAYS}:{remote.SEND_S * 1e3:g}"]  # the default only


def parse_hold(text: str) -> tuple[int, float]:
    """'RAYS:MS' -> (rays, seconds)."""
    try:
        rays, ms = text.split(":")
        hold = int(rays), float(ms) / 1e3
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"a hold is RAYS:MS, such as 16384:8, not {text!r}") from None
    if hold[0] < 0 or hold[1] < 0:
        raise argparse.ArgumentTypeError(f"a hold cannot be negative: {text!r}")
    return hold


def _render(coord, scene, s: RenderSettings) -> tuple[dict, np.ndarray]:
    """One render on a started pool: its wall, CPU (shards and coordinator) and counts."""
    from nprt.workers.render import render

    c0, r0, t0 = coord.cpu_s, raylet_cpu_s(), time.perf_counter()
    result = render(scene, s, renderer=coord)
    wall, r1 = time.perf_counter() - t0, raylet_cpu_s()
    info, st = coord.info(), result.stats.to_dict()
    # This render's shard totals (`begin` zeroes them); the coordinator's add up over renders.
    shards = info["shard_stats"]
    coord_cpu = coord.cpu_s - c0
    shard_cpu = sum(x["cpu_s"] for x in shards)
    return {"mode": s.mode, "k": s.shards, "render_s": round(wall, 3),
            "cpu_s": round(shard_cpu + coord_cpu, 3), "coordinator_cpu_s": round(coord_cpu, 3),
            # the object store's work for parcels above the inline limit; not in cpu_s
            "raylet_cpu_s": None if None in (r0, r1) else round(r1 - r0, 3),
            "ray_threads_s": round(shard_cpu - sum(x["wavefront_cpu_s"] for x in shards), 3),
            "busy_fraction": [round(x["busy_s"] / wall, 3) for x in shards],
            "steps": sum(x["steps"] for x in shards), "parcels": sum(x["calls"] for x in shards),
            "transfers": st["total_transfers"], "ray_bytes": st["total_bytes"],
            "phase_cpu_s": st["phase_cpu_s"]}, result.film.image()


def bench(args) -> dict:
    from nprt.workers.render import make_renderer

    rows = []
    saved = (remote.HOLD_RAYS, remote.HOLD_S, remote.SEND_RAYS, remote.SEND_S, remote.EMIT_RAYS,
             remote.CARRY_RAYS, coordinator.COLLECT_ON_POLL_FROM_K)
    # (window or None: the coordinator's, hold, send, emit, carry, collect); the first is the
    # baseline
    settings = [(w, h, x, e, cr, c) for w in args.windows for h in args.holds
                for x in args.sends for e in args.emits for cr in args.carries
                for c in args.collects]
    try:
        for name in args.scenes:
            scene = stored_scene(name, args.size)
            base = dict(width=args.width, height=args.height, spp=args.spp, seed=0)
            ref, _, _ = run_one(scene.load(), RenderSettings(**base, shards=0))
            ref.update(scene=name)
            rows.append(ref)
            print(f"{name} reference {ref['render_s']:.2f} s, cpu {ref['cpu_s']:.2f} s", flush=True)
            for mode in args.modes:
                s = RenderSettings(**base, shards=args.k, mode=mode)
                coord = make_renderer(scene, s)
                try:
                    _render(coord, scene, s)  # the pool's first render: caches warm
                    first, default_window = None, coord.window
                    for r in range(args.rounds):
                        # alternate the order round by round: a drift in the machine's speed
                        # then falls on every setting alike
                        for window, hold, send, emit, carry, collect in settings[
                                ::1 - 2 * (r % 2)]:
                            coord.window = default_window if window is None else window
                            remote.HOLD_RAYS, remote.HOLD_S = hold
                            remote.SEND_RAYS, remote.SEND_S = send
                            remote.EMIT_RAYS, remote.CARRY_RAYS = emit, carry
                            coordinator.COLLECT_ON_POLL_FROM_K = {
                                "poll": 1, "now": 1 << 30}.get(collect, saved[-1])
                            row, img = _render(coord, scene, s)
                            first = img if first is None else first
                            row |= {"scene": name, "hold_rays": hold[0], "hold_ms": hold[1] * 1e3,
                                    "send_rays": send[0], "send_ms": send[1] * 1e3,
                                    "emit_rays": emit, "carry_rays": carry,
                                    "collect": collect,
                                    "window": coord.window,
                                    "wall_ratio": round(row["render_s"] / ref["render_s"], 3),
                                    "cpu_ratio": round(row["cpu_s"] / ref["cpu_s"], 3),
                                    "rays_per_parcel": round(row["transfers"]
                                                             / max(1, row["parcels"]), 1),
                                    "same_film_as_no_hold": bool(np.array_equal(img, first))}
                            rows.append(row)
                            print(_line(row), flush=True)
                finally:
                    coord.close()
    finally:
        (remote.HOLD_RAYS, remote.HOLD_S, remote.SEND_RAYS, remote.SEND_S,
         remote.EMIT_RAYS, remote.CARRY_RAYS, coordinator.COLLECT_ON_POLL_FROM_K) = saved
    return {"machine": {**machine(os.cpu_count()), "nproc": os.cpu_count()},
            "settings": vars(args) | {"out": str(args.out)}, "rows": rows}


def _line(r: dict) -> str:
    return (f"{r['scene']} {r['mode']} K={r['k']} window {r.get('window', 0):3d}, "
            f"hold {r['hold_rays']:6d} rays "
            f"{r['hold_ms']:4.1f} ms, send {r.get('send_rays', 0):5d} rays "
            f"{r.get('send_ms', 0.0):4.1f} ms, emit {r.get('emit_rays', 0):5d} rays, carry "
            f"{r.get('carry_rays', 0):5d}, "
            f"collect {r.get('collect', 'now')}: wall {r['render_s']:6.2f} s "
            f"({r['wall_ratio']:.2f}x) cpu "
            f"{r['cpu_s']:6.1f} s ({r['cpu_ratio']:.2f}x) coordinator "
            f"{r['coordinator_cpu_s']:5.2f} s steps {r['steps']:5d} parcels "
            f"{r['parcels']:5d} Ray threads {r['ray_threads_s']:5.1f} s raylet "
            f"{fmt_or_blank(r.get('raylet_cpu_s'), '.2f')} s same film {r['same_film_as_no_hold']}")


def markdown(res: dict) -> str:
    head = ("| scene | mode | K | window | hold rays | hold ms | send rays | send ms | "
            "emit rays | carry rays | collect | render s | vs reference | CPU s | CPU vs ref | "
            "coordinator CPU s | steps | parcels | rays / parcel | busy | Ray threads s | "
            "raylet CPU s | same film |\n"
            "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|"
            "---:|"
            "---:|---|---:|---:|---|\n")
    return head + "".join(
        f"| {r['scene']} | {r['mode']} | {r['k']} | {r.get('window', '')} | {r['hold_rays']} | "
        f"{r['hold_ms']:g} | "
        f"{r.get('send_rays', 0)} | {r.get('send_ms', 0.0):g} | "
        f"{fmt_or_blank(r.get('emit_rays'), 'd')} | {fmt_or_blank(r.get('carry_rays'), 'd')} | "
        f"{r.get('collect', '')} | "
        f"{r['render_s']:.2f} | "
        f"{r['wall_ratio']:.2f}x | {r['cpu_s']:.1f} | {r['cpu_ratio']:.2f}x | "
        f"{r['coordinator_cpu_s']:.2f}"
        f" | {r['steps']} | {r['parcels']} | {r['rays_per_parcel']:.0f} | "
        f"{', '.join(f'{b:.2f}' for b in r['busy_fraction'])} | {r['ray_threads_s']:.1f} | "
        f"{fmt_or_blank(r.get('raylet_cpu_s'), '.2f')} | "
        f"{'yes' if r['same_film_as_no_hold'] else 'NO'} |\n"
        for r in res["rows"] if r["k"])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["city", "forest"])
    ap.add_argument("--size", default="default")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=360)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--modes", nargs="+", default=["exact", "proxy"])
    ap.add_argument("--k", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=1, help="times through the settings")
    ap.add_argument("--holds", nargs="+", type=parse_hold, default=[parse_hold(h) for h in HOLDS],
                    help="RAYS:MS settings to compare, the first the baseline (default: "
                         + " ".join(HOLDS) + ")")
    ap.add_argument("--sends", nargs="+", type=parse_hold, default=[parse_hold(x) for x in SENDS],
                    help="RAYS:MS small-parcel waits, each tried with every hold (default: "
                         "the shipped one, " + " ".join(SENDS) + ")")
    ap.add_argument("--emits", nargs="+", type=int, default=[remote.EMIT_RAYS],
                    help="rays leaving that make a step send before it ends (0: at its end "
                         f"only), each tried with every other setting (default: "
                         f"{remote.EMIT_RAYS})")
    ap.add_argument("--carries", nargs="+", type=int, default=[remote.CARRY_RAYS],
                    help="fewer rays left after an iteration go on in the next step once "
                         "parcels wait (0: never), each tried with every other setting "
                         f"(default: {remote.CARRY_RAYS})")
    ap.add_argument("--windows", nargs="+", type=window_arg, default=[None],
                    help="live passes to compare, each with every hold and send (default: "
                         "the coordinator's own, nprt.workers.runtime.coordinator.live_window)")
    ap.add_argument("--collects", nargs="+", choices=["poll", "now", "shipped"],
                    default=["shipped"],
                    help="finished passes' films: on the shards' next polls at any K, "
                         "collected at once, or as shipped (on polls from K = "
                         f"{coordinator.COLLECT_ON_POLL_FROM_K}, "
                         "coordinator.COLLECT_ON_POLL_FROM_K), each tried with every other "
                         "setting (default: shipped)")
    add_output_flags(ap)
    args = smoke(ap.parse_args(), scenes=["forest"], size="tiny", width=32, height=24, spp=2,
                 modes=["exact"], k=2, holds=[(0, 0.0), (1 << 30, 0.002)],
                 sends=[(0, 0.0), (1 << 30, 1.0)], emits=[0, 1], carries=[1 << 30],
                 windows=[None, 1],
                 collects=["poll", "now"])
    res = bench(args)
    finish(res, args.out / "bench_step_hold.json", markdown=markdown, update_readme=False)


if __name__ == "__main__":
    main()
