"""The distributed runtime at production scale (issue 9), side by side in one run:

- render wall of exact and proxy with K=2 shards against the single-process reference
  (targets: <= 0.8x and <= 0.65x), each shard's busy fraction (>= 80 % at K=2; reported
  for K=4 and 8);
- 100k instances of a small mesh: load + partition + top level + K=2 shards ready
  (bench.render.bench_setup, target <= 5 s), and a real Ray pool started on that scene;
- a second job on a warm pool through the job manager: first tile after submission
  (target <= 1 s);
- checkpoint bytes written per rendered sample, before (the whole film after every pass)
  and after (every checkpoint_interval_s).

    python -m bench.render.bench_scale                       # forest and city, default size
    python -m bench.render.bench_scale --width 320 --spp 8   # quicker
"""

from __future__ import annotations

import argparse
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import ray

from bench.common import RESULTS, add_image_flags, finish, machine, quality, smoke, timed_render
from nprt.scene.io import load_any
from nprt.workers.runtime.pool import ShardPool
from nprt.workers.settings import RenderSettings

TARGETS = {"exact_ratio": 0.8, "proxy_ratio": 0.65, "busy_k2": 0.8, "setup_s": 5.0,
           "first_tile_s": 1.0}


def timed(scene, s: RenderSettings) -> dict:
    """Prepare (pool start, or reference set-up) then one timed render."""
    row, image, info = timed_render(scene, s)
    shards = info.get("shard_stats", [])
    return {**{k: row[k] for k in ("mode", "k", "prepare_s", "render_s", "total_bytes",
                                   "phase_s")},
            "busy": [x["busy_fraction"] for x in shards],
            "calls": [x["calls"] for x in shards], "image": image}


def bench_renders(name: str, args) -> list[dict]:
    scene = load_any(f"{name}:{args.size}" if args.size != "default" else name)
    base = dict(width=args.width, height=args.height, spp=args.spp, seed=0)
    rows = [timed(scene, RenderSettings(**base, shards=0))]
    for mode in ("exact", "proxy"):
        rows.append(timed(scene, RenderSettings(**base, shards=2, mode=mode)))
    for k in args.extra_k:
        rows.append(timed(scene, RenderSettings(**base, shards=k, mode="exact")))
    ref = rows[0]["image"]
    for r in rows:
        r["scene"] = name
        r["ratio"] = round(r["render_s"] / rows[0]["render_s"], 3)
        img = r.pop("image")
        if r is not rows[0]:
            r["quality"] = quality(ref, img)
        print(f"{name:10s} {r['mode']:9s} K={r['k']}  render {r['render_s']:7.2f} s  "
              f"ratio {r['ratio']:.2f}  busy {r['busy']}", flush=True)
    return rows


def bench_setup_100k(n: int) -> dict:
    from bench.render.bench_setup import run

    res = run(n=n, k=2, form="npz")
    # The same scene on a real Ray pool (world pickled through the object store,
    # shards started in their own processes and warmed).
    from bench.render.bench_setup import write_scene

    with tempfile.TemporaryDirectory() as d:
        path = write_scene(Path(d), n, form="npz")
        t0 = time.perf_counter()
        scene = load_any(str(path))
        pool = ShardPool(scene, RenderSettings(width=64, height=64, spp=1, shards=2))
        pool_s = time.perf_counter() - t0
        warm = [round(w, 3) for w in pool.warm_s]
        pool.close()
    return {"in_process": res, "ray_pool_s": round(pool_s, 3), "ray_pool_warm_s": warm}


def bench_warm_pool(scene_name: str, width: int) -> dict:
    """Two jobs on one scene through the job manager: time from submit() to the first
    tile event, cold pool and warm pool."""
    from nprt.service.config import ServiceSettings
    from nprt.service.jobapi import JobApi
    from nprt.service.scenes import SceneStore
    from nprt.service.scheduler import Scheduler

    out = {}
    with tempfile.TemporaryDirectory() as d:
        cfg = ServiceSettings(data_dir=Path(d), max_concurrent_jobs=1, api_token=None,
                              ray_address=None)
        manager = JobApi(cfg, SceneStore(cfg)).start()  # stores and watches jobs
        scheduler = Scheduler(cfg).start()  # renders them
        try:
            for label, seed in (("cold", 1), ("warm", 2)):
                s = RenderSettings(width=width, height=width * 9 // 16, spp=8, shards=2,
                                   seed=seed)
                wake = threading.Event()
                t0 = time.perf_counter()
                rec, _ = manager.submit(scene_name, s)
                sub = manager.watch(rec.id, wake.set)
                first, ended = None, False
                while not ended:
                    wake.wait(600)
                    wake.clear()
                    for ev in sub.drain():
                        if ev["type"] == "tile" and first is None:
                            first = time.perf_counter() - t0
                        if ev["type"] == "state" and ev["job"].state in ("succeeded", "failed"):
                            ended = True
                sub.close()
                done = manager.get(rec.id)
                out[label] = {"first_tile_s": round(first, 3), "state": done.state,
                              "checkpoint_bytes": done.stats.get("checkpoint_bytes"),
                              "samples": s.width * s.height * s.spp,
                              "film_bytes": s.width * s.height * 32,
                              "passes": done.passes_total}
        finally:
            scheduler.stop()
            manager.stop()
    w = out["warm"]
    # Before: the manager wrote the whole film (sums + samples) after every pass.
    w["checkpoint_bytes_per_sample_before"] = round(w["film_bytes"] * w["passes"] /
                                                    w["samples"], 3)
    w["checkpoint_bytes_per_sample_after"] = round(w["checkpoint_bytes"] / w["samples"], 3)
    return out


def markdown(res: dict) -> str:
    a = res["args"]
    lines = [f"`python -m bench.render.bench_scale --width {a['width']} --height {a['height']} "
             f"--spp {a['spp']}` (`bench/results/bench_scale.json`), 2 cores, one run; "
             f"load average before: {res['machine']['load_average_before']}.", "",
             "| scene | renderer | K | prepare s | render s | vs reference | target | "
             "shard busy | calls | PSNR dB |",
             "| --- | --- | ---: | ---: | ---: | ---: | --- | --- | --- | ---: |"]
    for r in res["renders"]:
        target = {"exact": TARGETS["exact_ratio"], "proxy": TARGETS["proxy_ratio"]}.get(
            r["mode"]) if r["k"] == 2 else None
        verdict = "" if target is None else \
            f"<= {target} {'met' if r['ratio'] <= target else 'NOT met'}"
        q = r.get("quality", {}).get("psnr_db")
        lines.append(f"| {r['scene']} | {r['mode']} | {r['k']} | {r['prepare_s']:.2f} | "
                     f"{r['render_s']:.2f} | {r['ratio']:.2f}x | {verdict} | "
                     f"{', '.join(f'{b:.0%}' for b in r['busy'])} | "
                     f"{', '.join(map(str, r['calls']))} | {'' if q is None else q} |")
    s = res["setup"]
    crit = s["in_process"]
    lines += ["", f"**100k instances** (npz instance file, K=2): load + partition + top level "
              f"+ shards ready on the critical path {crit['critical_path_s']:.2f} s in process "
              f"(target <= {TARGETS['setup_s']} s: "
              f"{'met' if crit['critical_path_s'] <= TARGETS['setup_s'] else 'NOT met'}); "
              f"a real Ray pool on it (actors started, world through the object store, "
              f"kernels warmed) {s['ray_pool_s']:.2f} s."]
    w = res["warm_pool"]
    lines += ["", f"**Warm pool** (`{res['args']['warm_scene']}` through the job manager): "
              f"first tile {w['cold']['first_tile_s']:.2f} s after submission on a cold pool, "
              f"**{w['warm']['first_tile_s']:.2f} s on a warm one** (target <= "
              f"{TARGETS['first_tile_s']} s: "
              f"{'met' if w['warm']['first_tile_s'] <= TARGETS['first_tile_s'] else 'NOT met'})."
              f" Checkpoint bytes per rendered sample: "
              f"{w['warm']['checkpoint_bytes_per_sample_before']} before (the whole film after "
              f"each of {w['warm']['passes']} passes), "
              f"{w['warm']['checkpoint_bytes_per_sample_after']} after (every 5 s)."]
    return "\n".join(lines)


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in res["renders"] if r["mode"] != "reference"]
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4))
    labels = [f"{r['scene']}\n{r['mode']} K={r['k']}" for r in rows]
    x = np.arange(len(rows))
    ax0.bar(x, [r["ratio"] for r in rows], color=["C0" if r["mode"] == "exact" else "C1"
                                                   for r in rows])
    ax0.axhline(1.0, color="k", lw=0.8, label="reference (1 core)")
    ax0.axhline(TARGETS["exact_ratio"], color="C0", ls="--", lw=0.8, label="exact target")
    ax0.axhline(TARGETS["proxy_ratio"], color="C1", ls="--", lw=0.8, label="proxy target")
    ax0.set_xticks(x, labels, fontsize=7)
    ax0.set_ylabel("render wall / reference")
    ax0.legend(fontsize=7)
    for i, r in enumerate(rows):
        ax1.scatter([i] * len(r["busy"]), r["busy"], color="C2")
    ax1.axhline(TARGETS["busy_k2"], color="k", ls="--", lw=0.8, label="K=2 target")
    ax1.set_xticks(x, labels, fontsize=7)
    ax1.set_ylim(0, 1.05)
    ax1.set_ylabel("shard busy fraction")
    ax1.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_image_flags(ap)
    ap.add_argument("--extra-k", type=int, nargs="*", default=[4, 8],
                    help="exact renders at these K too, for the busy fraction")
    ap.add_argument("--instances", type=int, default=100_000)
    ap.add_argument("--warm-scene", default="forest")
    ap.add_argument("--warm-width", type=int, default=320, help="image width of the warm-pool jobs")
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_scale.json")
    ap.add_argument("--no-readme", action="store_true")
    ap.add_argument("--smoke", action="store_true", help="tiny scene, for the CI smoke test")
    args = smoke(ap.parse_args(argv), scenes=["forest"], size="tiny", width=16, height=12, spp=1,
                 extra_k=[], instances=200, warm_scene="forest:tiny", warm_width=16)
    ray.init(include_dashboard=False, log_to_driver=False)
    res = {"machine": machine(int(ray.cluster_resources().get("CPU", 0))),
           "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
           "renders": []}
    for name in args.scenes:
        res["renders"] += bench_renders(name, args)
    res["setup"] = bench_setup_100k(args.instances)
    ray.shutdown()
    res["warm_pool"] = bench_warm_pool(args.warm_scene, args.warm_width)
    finish(res, args.out, plot=plot, markdown=markdown, section="bench_scale",
           intro="### Runtime at scale (issue 9)\n\n![]({png})\n\n",
           update_readme=not args.no_readme)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
