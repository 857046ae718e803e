"""When the shards of one render are busy: a traced render per window (the coordinator's live
passes), each shard's share of every time bin spent in wavefront steps, as a timeline.

A render that does not scale either runs out of work at its end (idle in the last bins:
the last passes), or starves in its middle (shards waiting for each other's parcels: too
few passes live, or steps too small), or is busy throughout and needs less CPU to go
faster. The plot tells these apart at a glance; the table gives each shard's busy share of
the wall and the mean busy share in the first, middle and last third of the render.

    python -m bench.render.bench_busy --scene city --mode exact --k 2 --windows 12 48
    python -m bench.render.bench_busy --smoke
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from bench.common import add_output_flags, finish, machine, smoke, stored_scene, window_arg
from nprt.workers.settings import RenderSettings


def busy_bins(steps: list[dict], k: int, t0: float, wall: float, bin_s: float) -> np.ndarray:
    """(k, bins) float64: the share of each bin shard k spent in steps (trace records:
    shard, start, end, on time.time()'s clock; t0: the render's start on it)."""
    edges = np.arange(0.0, wall + bin_s, bin_s)
    busy = np.zeros((k, len(edges) - 1))
    lo, hi = edges[:-1], edges[1:]
    for st in steps:
        a, b = st["start"] - t0, st["end"] - t0
        busy[st["shard"]] += np.clip(np.minimum(b, hi) - np.maximum(a, lo), 0.0, None)
    return busy / bin_s


def bench(args) -> dict:
    from nprt.workers.render import make_renderer, render

    scene = stored_scene(args.scene, args.size)
    s = RenderSettings(width=args.width, height=args.height, spp=args.spp, seed=0,
                       shards=args.k, mode=args.mode)
    coord = make_renderer(scene, s, trace=True)
    rows = []
    try:
        render(scene, s, renderer=coord)  # the pool's first render: caches warm
        default = coord.window
        for window in args.windows:
            coord.window = default if window is None else window
            t0, p0 = time.time(), time.perf_counter()
            render(scene, s, renderer=coord)
            wall = time.perf_counter() - p0
            steps = [x for x in coord.trace.to_dict()["steps"] if x["start"] >= t0]
            busy = busy_bins(steps, args.k, t0, wall, args.bin_s)
            thirds = [float(part.mean()) if part.size else 0.0
                      for part in np.array_split(busy, 3, axis=1)]
            rows.append({"window": coord.window, "render_s": round(wall, 3),
                         "steps": len(steps), "bin_s": args.bin_s,
                         "busy_fraction": [round(float(sum(x["end"] - x["start"] for x in steps
                                                           if x["shard"] == i)) / wall, 3)
                                           for i in range(args.k)],
                         "busy_by_third": [round(x, 3) for x in thirds],
                         "busy_bins": np.round(busy, 3).tolist()})
            print(_line(rows[-1]), flush=True)
    finally:
        coord.close()
    return {"machine": {**machine(os.cpu_count()), "nproc": os.cpu_count()},
            "settings": vars(args) | {"out": str(args.out)}, "rows": rows}


def _line(r: dict) -> str:
    return (f"window {r['window']:4d}: wall {r['render_s']:6.2f} s, steps {r['steps']:5d}, busy "
            f"{', '.join(f'{b:.2f}' for b in r['busy_fraction'])}; by third "
            f"{', '.join(f'{b:.2f}' for b in r['busy_by_third'])}")


def markdown(res: dict) -> str:
    a = res["settings"]
    head = (f"{a['scene']} {a['mode']}, K = {a['k']}, {a['width']}x{a['height']}, {a['spp']} "
            "spp\n\n| window | render s | steps | busy per shard | busy: first / middle / "
            "last third |\n|---:|---:|---:|---|---|\n")
    return head + "".join(
        f"| {r['window']} | {r['render_s']:.2f} | {r['steps']} | "
        f"{', '.join(f'{b:.2f}' for b in r['busy_fraction'])} | "
        f"{' / '.join(f'{b:.2f}' for b in r['busy_by_third'])} |\n" for r in res["rows"])


def plot(res: dict, png) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = res["rows"]
    fig, axes = plt.subplots(len(rows), 1, figsize=(9, 2.4 * len(rows)), squeeze=False,
                             sharex=True)
    for ax, r in zip(axes[:, 0], rows, strict=True):
        busy = np.array(r["busy_bins"])
        t = (np.arange(busy.shape[1]) + 0.5) * r["bin_s"]
        for i, b in enumerate(busy):
            ax.plot(t, b, lw=1.2, label=f"shard {i}")
        ax.set_ylim(0, 1.05)
        ax.set_ylabel("busy share")
        ax.set_title(f"window {r['window']}: {r['render_s']:.2f} s", fontsize=10)
        ax.legend(loc="lower left", fontsize=7, ncol=min(8, len(busy)))
    axes[-1, 0].set_xlabel("seconds into the render")
    a = res["settings"]
    fig.suptitle(f"{a['scene']} {a['mode']} K = {a['k']}: time in wavefront steps", fontsize=11)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="city")
    ap.add_argument("--size", default="default")
    ap.add_argument("--mode", default="exact", choices=["exact", "proxy"])
    ap.add_argument("--k", type=int, default=2)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=360)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--windows", nargs="+", type=window_arg, default=[None],
                    help="live passes, one traced render each (default: the coordinator's)")
    ap.add_argument("--bin-s", type=float, default=0.5, help="timeline bin, seconds")
    add_output_flags(ap)
    args = smoke(ap.parse_args(), scene="forest", size="tiny", width=32, height=24, spp=2,
                 windows=[None, 1], bin_s=0.05)
    if args.bin_s <= 0:
        ap.error("--bin-s must be positive")
    res = bench(args)
    finish(res, args.out / f"bench_busy_{args.scene}_{args.mode}_k{args.k}.json", plot=plot,
           markdown=markdown, update_readme=False)


if __name__ == "__main__":
    main()
