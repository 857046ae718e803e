"""The cost of a shard visit, without Ray: K Shards in this one process, stepped in turn, each
step's parcels handed straight to their target, passes admitted as the coordinator admits
them (one live pass per tile, the coordinator's window) and completed by weight
throwing. Everything is one thread, so process CPU is exact and nothing waits.

It splits the distributed renderer's extra CPU in two: what the wavefront itself costs for
K shards (rays visit several shards in exact forwarding, every visit walks the top level,
intersects, routes and copies the ray again: the glue grows with visits) and, by difference
with bench_strong_scaling's CPU at the same K, what Ray adds (calls, serialization, threads).

Per row: CPU seconds over all shards and per camera path, shard visits per camera ray
(rays entering steps / camera rays), CPU per visit, the phase split, and the ratio to the
one-shard CPU of the same image (the reference's wavefront).

The steps are recorded as a step trace and replayed on K dedicated cores by
bench/network/netmodel.py, each step taking its in-process CPU plus Ray's CPU for the
parcels it sent and received (measured at the start of the run, bench/render/raycalls.py):
a render wall for K cores that neither this host's two cores nor Ray's threads on them
distort. It is a model: the grouping of rays into steps is this loop's, not a live run's.

    python -m bench.render.bench_visits                          # forest, city; 320x180 8 spp
    python -m bench.render.bench_visits --scenes forest --ks 1 4 --modes exact
    python -m bench.render.bench_visits --scenes city --ks 1 8 --modes proxy --step-cap 500
    python -m bench.render.bench_visits --smoke
"""

from __future__ import annotations

import argparse
import os
import time
from fractions import Fraction

import numpy as np

from bench.common import (
    add_image_flags,
    add_output_flags,
    finish,
    machine,
    placeable_ks,
    smoke,
    stored_scene,
)
from bench.network.netmodel import film_bytes, replay
from bench.render.bench_strong_scaling import FALLBACK_RPC_S, MODEL_LINK_BPS
from bench.render.raycalls import parcel_cost, with_ray_cost
from bench.render.vtime import collect_pass
from nprt.workers.passes import count_tiles, iter_passes
from nprt.workers.runtime import remote
from nprt.workers.runtime.coordinator import live_window
from nprt.workers.runtime.protocol import sum_credits
from nprt.workers.runtime.remote import carry_when
from nprt.workers.settings import SPP_PER_PASS, RenderSettings
from nprt.workers.stats.counters import RenderStats
from nprt.workers.wavefront.inprocess import shards_in_process
from nprt.workers.wavefront.shard import Shard


def run(shards: list[Shard], s: RenderSettings, carry: bool = True, cap: int = 0) -> dict:
    """Render every pass of `s` on `shards`; returns CPU, visits, phases and the film.
    carry: what a shard's step has left after an iteration waits for its next step when
    rays for it were sent this round (`Shard.step`, carry; `remote.CARRY_RAYS`), as the
    runtime does. cap: a step
    takes parcels up to this many rays, the rest wait a round (0: no cap): the same rays
    in more, smaller steps, as on dedicated cores, whose extra CPU is the steps' fixed
    cost."""
    k, tiles = len(shards), count_tiles(s)
    window = live_window(k, tiles)
    inbox: list[list] = [[] for _ in range(k)]  # per shard: (orders, parcel or None, credits)
    waiting = list(iter_passes(s))
    live: dict[int, Fraction] = {}  # pass index -> weight back so far
    film = np.zeros((s.height * s.width, 3))
    times, steps, rays_in, camera = RenderStats(), 0, 0, 0
    counters: dict[str, int] = {}  # the passes' statistics counters, summed
    trace = {"k": k, "steps": [], "admitted": []}  # calltrace.StepTrace's format
    step_of = [0] * k
    c0 = time.process_time()
    while waiting or live:
        busy_tiles = {i % tiles for i in live}
        for p in [p for p in waiting if len(live) < window]:
            if p.index % tiles in busy_tiles or len(live) >= window:
                continue
            waiting.remove(p)
            busy_tiles.add(p.index % tiles)
            live[p.index] = Fraction(0)
            trace["admitted"].append(p.index)
            inbox[p.index % k].append(((p,), None, {p.index: Fraction(1)}))
            camera += p.n_paths
        # Every shard steps on what arrived by the end of the last round, as K shards on K
        # cores would at once: a parcel sent this round waits for the next (no chain of
        # steps within a round, which the model would replay as serial).
        arrived, inbox = inbox, [[] for _ in range(k)]
        for sid in range(k) if cap else ():  # what is past the cap waits, orders never
            kept, n = [], 0
            for item in arrived[sid]:
                rays = 0 if item[1] is None else item[1].n_rays
                if kept and not item[0] and n + rays > cap:
                    inbox[sid].append(item)
                else:
                    kept.append(item)
                    n += rays
            arrived[sid] = kept
        for sid, sh in enumerate(shards):
            if not arrived[sid]:
                continue
            work = arrived[sid]
            credits = sum_credits(c for _, _, c in work)
            parcels = [x for _, x, _ in work if x is not None]
            orders = [o for os_, _, _ in work for o in os_]
            t0 = time.process_time()
            res = sh.step(orders, parcels, credits, carry=carry_when(
                lambda box=inbox[sid]: bool(box), remote.CARRY_RAYS if carry else 0))
            dt = time.process_time() - t0
            steps += 1
            rays_in += res.rays_in
            times.merge(res.times)
            sent = []
            for target, out in enumerate(res.parcels):
                if out is not None:  # every parcel leaves at the step's end (no emit)
                    out.source = (sid, step_of[sid], None)
                    inbox[target].append(((), out, out.credits))
                    sent.append((target, out.n_rays, out.nbytes, None))
            trace["steps"].append({
                "shard": sid, "step": step_of[sid], "cpu_s": dt, "busy_s": dt,
                "orders": [o.index for o in orders], "passes": sorted(credits),
                "inputs": [(*x.source[:2], x.n_rays, x.nbytes, x.source[2]) for x in parcels],
                "outputs": sent})
            step_of[sid] += 1
            for i, w in res.returned.items():
                live[i] += w
        for i in [i for i, w in live.items() if w == 1]:
            del live[i]
            collect_pass(shards, s, i, film, counters)
    cpu = time.process_time() - c0
    per_shard = np.zeros(k)
    for st in trace["steps"]:
        per_shard[st["shard"]] += st["cpu_s"]
    return {"cpu_s": cpu, "shard_cpu_s": per_shard, "steps": steps, "camera_rays": camera,
            "rays_in": rays_in,
            "phase_cpu_s": {n: round(v, 4) for n, v in sorted(times.phase_cpu_s.items())},
            "counters": counters, "film": film, "trace": trace, "window": window}


def model_wall(r: dict, s: RenderSettings, cost: dict) -> float:
    """The run's steps replayed on K dedicated cores, Ray's per-parcel CPU added."""
    return replay(r["trace"], MODEL_LINK_BPS, FALLBACK_RPC_S, r["window"], film_bytes(s),
                  with_ray_cost(r["trace"], cost)).makespan_s


def bench(args) -> dict:
    cost = parcel_cost(calls=20 if args.smoke else 300, repeats=1 if args.smoke else 3)
    print(f"Ray per parcel: send {1e3 * cost['send_s']:.3f} ms + "
          f"{1e9 * cost['send_s_per_byte']:.2f} ms/MB, receive {1e3 * cost['receive_s']:.3f} "
          f"ms + {1e9 * cost['receive_s_per_byte']:.2f} ms/MB", flush=True)
    rows = []
    for name in args.scenes:
        scene = stored_scene(name, args.size).load()
        base = dict(width=args.width, height=args.height, spp=args.spp, seed=0,
                    spp_per_pass=args.spp_per_pass)
        one = None
        for mode in args.modes:
            for k in placeable_ks(args.ks, scene, name):
                s = RenderSettings(**base, shards=k, mode=mode)
                r = run(shards_in_process(scene, s), s, carry=not args.no_carry,
                        cap=args.step_cap)
                if k == 1 and one is None:
                    one = r
                elif k == 1:
                    one = min(one, r, key=lambda x: x["cpu_s"])
                row = {"scene": name, "mode": mode, "k": k, "cpu_s": round(r["cpu_s"], 3),
                       "us_per_path": round(1e6 * r["cpu_s"] / r["camera_rays"], 2),
                       "visits_per_path": round(r["rays_in"] / r["camera_rays"], 3),
                       "us_per_visit": round(1e6 * r["cpu_s"] / max(r["rays_in"], 1), 3),
                       "steps": r["steps"], "phase_cpu_s": r["phase_cpu_s"],
                       # the busiest shard's CPU over the mean: bounds the wall on K cores
                       "imbalance": round(float(r["shard_cpu_s"].max()
                                                / r["shard_cpu_s"].mean()), 3),
                       "model_s": round(model_wall(r, s, cost), 3)}
                if one is not None:
                    row["cpu_vs_one_shard"] = round(r["cpu_s"] / one["cpu_s"], 3)
                    row["model_vs_one_shard"] = round(row["model_s"] / one["cpu_s"], 3)
                    if mode == "exact" or k == 1:
                        row["same_film_as_one_shard"] = bool(np.array_equal(r["film"],
                                                                             one["film"]))
                rows.append(row)
                print(_line(row), flush=True)
    return {"machine": machine(os.cpu_count()), "settings": vars(args) | {"out": str(args.out)},
            "ray_parcel_cost": cost, "rows": rows}


def _line(r: dict) -> str:
    return (f"{r['scene']} {r['mode']:6s} K={r['k']:2d} cpu {r['cpu_s']:7.2f} s  "
            f"{r['us_per_path']:6.2f} us/path  {r['visits_per_path']:5.2f} visits/path  "
            f"{r['us_per_visit']:6.3f} us/visit  x{r.get('cpu_vs_one_shard', 1.0):.2f}  "
            f"model on K cores {r['model_s']:.2f} s = x{r.get('model_vs_one_shard', 1.0):.2f}")


PHASES = ("receive", "generate", "top_level", "local_intersect", "proxy", "shade", "send",
          "bookkeeping")


def markdown(res: dict) -> str:
    c = res["ray_parcel_cost"]
    out = [f"Ray per parcel (this run): send {1e3 * c['send_s']:.2f} ms + "
           f"{1e9 * c['send_s_per_byte']:.2f} ms/MB, receive {1e3 * c['receive_s']:.2f} ms + "
           f"{1e9 * c['receive_s_per_byte']:.2f} ms/MB. *model* is the render wall on K "
           "dedicated cores (steps replayed with Ray's cost added), against the one-shard CPU; "
           "*busiest / mean shard* is the CPU of the busiest shard over the mean, and *bound* "
           "that shard's CPU against the one-shard CPU: no schedule on K cores beats it (Ray's "
           "cost left out). The model keeps this loop's grouping of rays into rounds, so it "
           "sits above what a runtime that regroups as rays arrive can reach: the wall on K "
           "cores lies between the two.",
           "",
           "| scene | mode | K | CPU s | vs 1 shard | us / path | visits / path | us / visit | "
           + " | ".join(PHASES) + " | same film | busiest / mean shard | bound | model s | "
           "model vs 1 shard |",
           "|---|---|---:|---:|---:|---:|---:|---:|" + "---:|" * len(PHASES)
           + "---|---:|---:|---:|---:|"]
    for r in res["rows"]:
        ph = " | ".join(f"{r['phase_cpu_s'].get(p, 0.0):.2f}" for p in PHASES)
        same = r.get("same_film_as_one_shard")
        out.append(f"| {r['scene']} | {r['mode']} | {r['k']} | {r['cpu_s']:.2f} | "
                   f"{r.get('cpu_vs_one_shard', 1.0):.2f}x | {r['us_per_path']:.2f} | "
                   f"{r['visits_per_path']:.2f} | {r['us_per_visit']:.3f} | {ph} | "
                   f"{'' if same is None else ('yes' if same else 'NO')} | "
                   f"{r['imbalance']:.2f} | {_bound(r, res):.2f}x | {r['model_s']:.2f} | "
                   f"{r.get('model_vs_one_shard', 1.0):.2f}x |")
    return "\n".join(out)


def _bound(r: dict, res: dict) -> float:
    """The busiest shard's CPU over the one-shard CPU of the scene (the baseline of
    `cpu_vs_one_shard`); NaN for a run without K = 1."""
    ratio = r.get("cpu_vs_one_shard")
    return float("nan") if ratio is None else r["imbalance"] * ratio / r["k"]


def plot(res: dict, png) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for (scene, mode), style in zip(sorted({(r["scene"], r["mode"]) for r in res["rows"]}),
                                    ("o-", "s-", "^-", "v-", "d-", "x-"), strict=False):
        rs = [r for r in res["rows"] if (r["scene"], r["mode"]) == (scene, mode)]
        ks = [r["k"] for r in rs]
        axes[0].plot(ks, [r.get("cpu_vs_one_shard", 1.0) for r in rs], style,
                     label=f"{scene} {mode}")
        axes[1].plot(ks, [r["visits_per_path"] for r in rs], style, label=f"{scene} {mode}")
        axes[2].plot(ks, [r.get("model_vs_one_shard", 1.0) for r in rs], style,
                     label=f"{scene} {mode}")
        axes[2].plot(ks, [_bound(r, res) for r in rs], style[0] + "--",
                     label=f"{scene} {mode}: busiest shard")
    axes[2].plot([1, 16], [1, 1 / 16], ":", color="gray", label="ideal")
    axes[2].set_yscale("log", base=2)
    for ax, what in zip(axes, ("CPU / one shard's CPU", "shard visits per camera path",
                               "wall on K cores / one shard's CPU (model; bound dashed)"),
                        strict=True):
        ax.set_xscale("log", base=2)
        ax.set_xlabel("shards K (one process, no Ray)")
        ax.set_ylabel(what)
        ax.legend()
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.render.bench_visits",
                                 description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    add_image_flags(ap, 320, 180, 8)
    ap.add_argument("--spp-per-pass", type=int, default=SPP_PER_PASS)
    ap.add_argument("--modes", nargs="+", default=["exact", "proxy"])
    ap.add_argument("--no-carry", action="store_true",
                    help="no step carries what it has left after an iteration into the "
                         "shard's next step (remote.CARRY_RAYS)")
    ap.add_argument("--step-cap", type=int, default=0,
                    help="rays a step takes at most, the rest wait a round (0: no cap): "
                         "the cost of smaller steps")
    ap.add_argument("--ks", type=int, nargs="+", default=[1, 2, 4, 8, 16])
    add_output_flags(ap)
    args = smoke(ap.parse_args(argv), scenes=["forest"], size="tiny", width=32, height=24,
                 spp=1, spp_per_pass=1, ks=[1, 2], modes=["exact"], step_cap=16)
    res = bench(args)
    finish(res, args.out / "bench_visits.json", plot=plot, markdown=markdown,
           section="bench_visits", update_readme=not args.no_readme,
           intro="`python -m bench.render.bench_visits` (`{json}`):\n\n![]({png})\n\n")


if __name__ == "__main__":
    main()
