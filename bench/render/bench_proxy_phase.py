"""Where a proxy-mode shard's `proxy` phase goes, against the one-shard CPU of the same image:
K in-process Shards (bench_visits.run, no Ray, one thread, so process CPU is exact), with
the proxy phase's parts timed around their calls:

- walk: the compiled walk of each asked ray over the boxes this shard does not hold
  (`proxy_pairs.walk_queries`), per ray walked;
- known: the exact intersection of remote instances whose base mesh this shard holds
  (`proxy_query.known_hits`);
- nets: onnxruntime (`Proxy.run_even`), per call and per row, visibility and depth;
- decide: the per-ray rules over the answers (`proxy_pairs.decide_queries`);
- the rest of the phase: Python glue and the compiled net-row passes.

It also counts the pairs a proxy answered whose box the ray enters only after its final
closest hit: they cannot change an answer, and a nearest-box-first order of asking would
skip them (at the price of more onnxruntime calls). With --repeats, it counts the pairs
asked before, on this or another shard (the same ray, origin and direction, and the same
box): the answers a ray could carry from shard to shard instead (this adds CPU to the run).

The phase is the whole of what proxy mode adds at K = 2 in forest: without it the K = 2
CPU is about the one-shard CPU (bench/README.md "What proxy mode's CPU is made of").

    python -m bench.render.bench_proxy_phase                    # forest, city, windy; K 2 8
    python -m bench.render.bench_proxy_phase --scenes city --ks 2 --width 320 --height 180
    python -m bench.render.bench_proxy_phase --scenes forest city --ks 8 --repeats
    python -m bench.render.bench_proxy_phase --smoke
"""

from __future__ import annotations

import argparse
import os
import time
from contextlib import contextmanager

import numpy as np

from bench.common import add_image_flags, add_output_flags, finish, machine, smoke, stored_scene
from bench.render.bench_visits import run
from nprt.proxies.inference import Proxy
from nprt.workers.routing import proxy_pairs, proxy_query
from nprt.workers.settings import RenderSettings
from nprt.workers.wavefront.inprocess import shards_in_process

PARTS = ("walk", "known", "nets", "decide")


class _Meter:
    """CPU seconds and counts of the proxy phase's parts, gathered by wrapping the module
    functions the phase calls (`timed`); `counts` : rays walked, pairs, net calls and rows,
    and the needless pairs (box entered after the ray's final closest hit)."""

    def __init__(self, repeats: bool = False):
        self.cpu = dict.fromkeys(PARTS, 0.0)
        self.counts = dict.fromkeys(("rays_walked", "pairs", "net_calls", "visibility_rows",
                                     "depth_rows", "needless_pairs", "needless_depth_rows"), 0)
        # (origin, direction, box) of every pair asked so far, as 96 bytes: with repeats
        self._asked: set[bytes] | None = set() if repeats else None
        if repeats:
            self.counts["repeat_pairs"] = 0

    def _count_repeats(self, origin, direction, boxes, ray, inst) -> None:
        """Pairs (ray (p,), inst (p,) positions into boxes (k, 2, 3) float64) asked before."""
        if self._asked is None or len(ray) == 0:
            return
        keys = np.ascontiguousarray(np.concatenate(
            [np.asarray(origin, np.float64)[ray], np.asarray(direction, np.float64)[ray],
             boxes[inst].reshape(len(inst), 6)], axis=1))
        for key in keys.view(np.dtype((np.void, keys.shape[1] * 8))).ravel():
            b = key.tobytes()
            if b in self._asked:
                self.counts["repeat_pairs"] += 1
            else:
                self._asked.add(b)

    def _timed(self, part: str, fn):
        def wrapped(*args):
            c0 = time.process_time()
            out = fn(*args)
            self.cpu[part] += time.process_time() - c0
            return out
        return wrapped

    @contextmanager
    def timed(self):
        """The proxy phase's functions wrapped for the duration; restored after."""
        walk, known = proxy_pairs.walk_queries, proxy_query.known_hits
        decide, run_even = proxy_pairs.decide_queries, Proxy.run_even
        timed_walk, timed_decide = self._timed("walk", walk), self._timed("decide", decide)
        timed_nets = self._timed("nets", run_even)

        def walk_counted(*args):
            out = timed_walk(*args)
            self.counts["rays_walked"] += len(args[0])
            self.counts["pairs"] += len(out[0])
            self._count_repeats(args[0], args[1], args[3], out[0], out[1])
            return out

        def nets_counted(proxy, net, x):
            self.counts["net_calls"] += proxy.calls(len(x))
            self.counts[f"{net}_rows"] += len(x)
            return timed_nets(proxy, net, x)

        def decide_counted(off, cut, ray, inst, mesh, internal, t_box, *rest):
            out = timed_decide(off, cut, ray, inst, mesh, internal, t_box, *rest)
            has, tp, best_t = rest[2], rest[4], rest[-2]  # lowered in place to the final hit
            needless = has & (np.where(internal, 0.0, t_box) >= best_t[ray])
            self.counts["needless_pairs"] += int(needless.sum())
            self.counts["needless_depth_rows"] += int((needless & np.isfinite(tp)).sum())
            return out

        proxy_pairs.walk_queries, proxy_query.known_hits = walk_counted, \
            self._timed("known", known)
        proxy_pairs.decide_queries, Proxy.run_even = decide_counted, nets_counted
        try:
            yield self
        finally:
            proxy_pairs.walk_queries, proxy_query.known_hits = walk, known
            proxy_pairs.decide_queries, Proxy.run_even = decide, run_even


def bench(args) -> dict:
    rows = []
    for name in args.scenes:
        scene = stored_scene(name, args.size).load()
        base = dict(width=args.width, height=args.height, spp=args.spp, seed=0)
        s1 = RenderSettings(**base, shards=1, mode="proxy")
        one = run(shards_in_process(scene, s1), s1)["cpu_s"]
        for k in args.ks:
            s = RenderSettings(**base, shards=k, mode="proxy")
            shards = shards_in_process(scene, s)
            with _Meter(args.repeats).timed() as meter:
                r = run(shards, s)
            phase = r["phase_cpu_s"].get("proxy", 0.0)
            c = meter.counts
            row = {"scene": name, "k": k, "one_shard_cpu_s": round(one, 3),
                   "cpu_s": round(r["cpu_s"], 3), "proxy_s": round(phase, 3),
                   **{f"{p}_s": round(v, 3) for p, v in meter.cpu.items()},
                   "rest_s": round(phase - sum(meter.cpu.values()), 3), **c,
                   "walk_ns_per_ray": round(1e9 * meter.cpu["walk"] / max(c["rays_walked"], 1), 1),
                   "net_ns_per_row": round(1e9 * meter.cpu["nets"]
                                           / max(c["visibility_rows"] + c["depth_rows"], 1), 1),
                   "net_us_per_call": round(1e6 * meter.cpu["nets"] / max(c["net_calls"], 1),
                                            1)}
            rows.append(row)
            print(_line(row), flush=True)
    return {"machine": machine(os.cpu_count()), "settings": vars(args) | {"out": str(args.out)},
            "rows": rows}


def _line(r: dict) -> str:
    one = r["one_shard_cpu_s"]
    return (f"{r['scene']} K={r['k']}: CPU {r['cpu_s']:.2f} s = {r['cpu_s'] / one:.2f}x one "
            f"shard; proxy phase {r['proxy_s']:.2f} s = {r['proxy_s'] / one:.2f}x (walk "
            f"{r['walk_s']:.2f}, known {r['known_s']:.2f}, nets {r['nets_s']:.2f}, decide "
            f"{r['decide_s']:.2f}, rest {r['rest_s']:.2f}); needless pairs "
            f"{r['needless_pairs'] / max(r['pairs'], 1):.0%}"
            + (f"; asked before {r['repeat_pairs'] / max(r['pairs'], 1):.1%}"
               if "repeat_pairs" in r else ""))


def markdown(res: dict) -> str:
    rep = all("repeat_pairs" in r for r in res["rows"])
    out = ["Seconds of process CPU; *x one shard* divides by the one-shard CPU of the same "
           "image (proxy mode, K = 1: the reference's wavefront). *needless*: pairs (and "
           "depth rows) whose box the ray enters after its final closest hit."
           + (" *asked before*: pairs asked before on some shard (the CPU then includes "
              "counting them)." if rep else ""), "",
           "| scene | K | CPU (x one shard) | proxy phase (x one shard) | walk | known | nets "
           "| decide | rest | rays walked, ns/ray | net rows (vis + depth), ns/row | net calls, "
           "us/call | needless pairs, depth rows |" + (" asked before |" if rep else ""),
           "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
           + ("---:|" if rep else "")]
    for r in res["rows"]:
        one = r["one_shard_cpu_s"]
        out.append(
            f"| {r['scene']} | {r['k']} | {r['cpu_s']:.2f} ({r['cpu_s'] / one:.2f}x) | "
            f"{r['proxy_s']:.2f} ({r['proxy_s'] / one:.2f}x) | {r['walk_s']:.2f} | "
            f"{r['known_s']:.2f} | {r['nets_s']:.2f} | {r['decide_s']:.2f} | "
            f"{r['rest_s']:.2f} | {r['rays_walked'] / 1e6:.1f} M, {r['walk_ns_per_ray']:.0f} | "
            f"{r['visibility_rows'] / 1e6:.2f} + {r['depth_rows'] / 1e6:.2f} M, "
            f"{r['net_ns_per_row']:.0f} | {r['net_calls']:,}, {r['net_us_per_call']:.0f} | "
            f"{r['needless_pairs'] / max(r['pairs'], 1):.0%}, "
            f"{r['needless_depth_rows'] / max(r['depth_rows'], 1):.0%} |"
            + (f" {r['repeat_pairs'] / max(r['pairs'], 1):.1%} |" if rep else ""))
    return "\n".join(out) + "\n"


def plot(res: dict, png) -> None:
    """Per scene and K, the proxy phase's parts stacked, in units of the one-shard CPU."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = res["rows"]
    labels = [f"{r['scene']}\nK = {r['k']}" for r in rows]
    fig, ax = plt.subplots(figsize=(max(5, 1.2 * len(rows) + 2), 4))
    bottom = np.zeros(len(rows))
    for part in (*PARTS, "rest"):
        share = np.array([r[f"{part}_s"] / r["one_shard_cpu_s"] for r in rows])
        ax.bar(labels, share, bottom=bottom, label=part)
        bottom += share
    ax.set_ylabel("proxy phase CPU / one shard's CPU")
    ax.set_title("What proxy mode's own phase costs (in process)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.render.bench_proxy_phase",
                                 description=__doc__.splitlines()[0])
    add_image_flags(ap)
    ap.set_defaults(scenes=["forest", "city", "windy"])
    ap.add_argument("--ks", type=int, nargs="+", default=[2, 8])
    ap.add_argument("--repeats", action="store_true",
                    help="count the pairs asked before (adds CPU: leave the timings aside)")
    add_output_flags(ap)
    # The demo's own size: a tiny scene gets no proxy (the policy replicates its meshes).
    args = smoke(ap.parse_args(argv), scenes=["forest"], width=32, height=24, spp=2, ks=[2])
    finish(bench(args), args.out / "bench_proxy_phase.json", plot=plot, markdown=markdown,
           update_readme=False)


if __name__ == "__main__":
    main()
