"""Animated frames (issue 10, item 4) on the `windy` demo (the forest with 4 trees and the
sun panel moving over 8 frames), side by side in one run: the reference, exact K and
proxy K each render every frame on one renderer made once.

Per configuration: the first frame's seconds (renderer start-up: shard actors, proxy plan,
kernel warm-up; plus its render) against the mean of the later frames (an instance table
and lights swap plus the render), the planner's proxy-cache lookups and the meshes sent to
training tasks during each frame (the plan is made once, when the pool starts: later
frames must make none), the shard actors' pids (the same on every frame) and, for exact, the largest
relative error against the reference over the frames (exact mode equals the reference).

    python -m bench.render.bench_frames                  # windy default, 160x120, 4 spp, K = 4
    python -m bench.render.bench_frames --size small --width 96
    python -m bench.render.bench_frames --train-proxies 1000   # adds proxy K trained from scratch

The shipped proxies cover the demo's meshes, so plain proxy mode trains nothing at all;
--train-proxies S adds a proxy configuration none is shipped for (width 16, S optimiser
steps of training each) on an empty cache, so its pool trains every proxy it needs (Ray tasks).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import ray

from bench.common import (
    RESULTS,
    add_render_flags,
    finish,
    machine,
    render_settings,
    smoke,
    start_ray,
)
from nprt.proxies.cache import ProxyCache
from nprt.proxies.tasks import RayTrainer
from nprt.scene.demos import make_demo
from nprt.scene.store import open_scene
from nprt.workers.frames import render_frames
from nprt.workers.render import make_renderer
from nprt.workers.settings import ProxySettings


class ProxyCalls:
    """Counts, in this driver, the planner's proxy-cache lookups and the meshes sent to
    training tasks (`RayTrainer`): a pool plans and trains there, and nowhere else."""

    def __init__(self):
        self.lookups = self.trainings = 0
        self._real = ProxyCache.get, RayTrainer.__call__

    def __enter__(self) -> ProxyCalls:
        get, call = self._real

        def counted_get(cache, *a, **kw):
            self.lookups += 1
            return get(cache, *a, **kw)

        def counted_call(trainer, meshes, *a, **kw):
            self.trainings += len(meshes)
            return call(trainer, meshes, *a, **kw)

        ProxyCache.get, RayTrainer.__call__ = counted_get, counted_call
        return self

    def __exit__(self, *exc) -> None:
        ProxyCache.get, RayTrainer.__call__ = self._real


def run_config(scene, s, fresh_dir: Path | None = None) -> tuple[dict, dict]:
    """One configuration over every frame (fresh_dir: train proxies into this empty
    cache; their config is not a shipped one). Returns (row, {frame: image (h, w, 3)})."""
    images, frames = {}, []
    with ProxyCalls() as calls:
        t0 = time.perf_counter()
        renderer = make_renderer(scene, s, proxy_dir=fresh_dir)
        setup_s = time.perf_counter() - t0
        try:
            before = (calls.lookups, calls.trainings)
            for done in render_frames(scene, s, range(scene.frames), renderer=renderer):
                now = (calls.lookups, calls.trainings)
                info = done.result.info
                frames.append({
                    "frame": done.frame, "seconds": round(done.wall_s, 4),
                    "render_s": info["wall_s"],
                    "proxy_lookups": now[0] - before[0], "proxy_trainings": now[1] - before[1],
                    "pids": [i["pid"] for i in info.get("shard_stats", [])]})
                before = now
                images[done.frame] = done.result.film.image()
            plan = renderer.info().get("proxy_plan")
        finally:
            renderer.close()
        setup_lookups, setup_trainings = calls.lookups, calls.trainings
    later = [f["seconds"] for f in frames[1:]]
    first = setup_s + frames[0]["seconds"]
    mode = s.mode if s.shards else "reference"
    row = {"mode": f"{mode} (trained)" if fresh_dir else mode, "k": s.shards,
           "setup_s": round(setup_s, 4), "first_frame_s": round(first, 4),
           "later_frame_s_mean": round(float(np.mean(later)), 4),
           "later_over_first": round(float(np.mean(later)) / first, 4),
           "first_frame_render_s": frames[0]["render_s"],
           "later_render_s_mean": round(float(np.mean([f["render_s"] for f in frames[1:]])), 4),
           "proxy_lookups_at_setup": setup_lookups - sum(f["proxy_lookups"] for f in frames),
           "proxy_trainings_at_setup": setup_trainings - sum(f["proxy_trainings"]
                                                            for f in frames),
           "proxy_lookups_after_frame_0": sum(f["proxy_lookups"] for f in frames[1:]),
           "proxy_trainings_after_frame_0": sum(f["proxy_trainings"] for f in frames[1:]),
           "same_actors_every_frame": all(f["pids"] == frames[0]["pids"] for f in frames),
           "proxy_plan_counts": None if plan is None else plan["counts"],
           "frames": frames}
    return row, images


def markdown(res: dict) -> str:
    s = res["settings"]
    train = res.get("train_proxies")
    cmd = (f"python -m bench.render.bench_frames --size {res['size']} --width {s['width']} --spp "
           f"{s['spp']} --shards {res['shards']}")
    cmd += f" --train-proxies {train}" if train else ""
    lines = [
        f"`{cmd}` (`bench/results/{res['file']}`), load average before "
        f"{', '.join(f'{x:.2f}' for x in res['machine']['load_average_before'])} and after "
        f"{', '.join(f'{x:.2f}' for x in res['machine']['load_average_after'])} on "
        f"{res['machine']['cpus']} cores; {res['scene']['frames']} frames of "
        f"`{res['scene']['name']}` ({res['scene']['instances']} instances, "
        f"{res['moving']} moving, and the sun), {s['width']}x{s['height']}, {s['spp']} spp, "
        f"{s['bounces']} bounces. Proxy mode uses the shipped proxies"
        + (f"; *proxy (trained)* a configuration none is shipped for (width 16, {train:g} s "
           f"of training each) on an empty cache, so its pool trains each proxy it needs as "
           f"Ray tasks while it starts. Shards open the scene as metadata from the scene "
           f"cache; the reference renders it in memory." if train else "."),
        "",
        "| renderer | K | first frame s (set-up + render) | later frames s (mean) | later / first "
        "| render s: first / later mean | proxy lookups / trainings: set-up, after frame 0 "
        "| same actors | max rel. error vs reference |",
        "| --- | ---: | ---: | ---: | ---: | --- | --- | --- | ---: |",
    ]
    for r in res["rows"]:
        err = r.get("max_rel_error_vs_reference")
        lines.append(
            f"| {r['mode']} | {r['k']} | {r['first_frame_s']:.2f} ({r['setup_s']:.2f} + "
            f"{r['first_frame_render_s']:.2f}) | {r['later_frame_s_mean']:.2f} | "
            f"{r['later_over_first']:.2f} | {r['first_frame_render_s']:.2f} / "
            f"{r['later_render_s_mean']:.2f} | {r['proxy_lookups_at_setup']} / "
            f"{r['proxy_trainings_at_setup']}, {r['proxy_lookups_after_frame_0']} / "
            f"{r['proxy_trainings_after_frame_0']} | "
            f"{'yes' if r['same_actors_every_frame'] else 'no'} | "
            f"{'' if err is None else f'{err:.1e}'} |")
    return "\n".join(lines)


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.5))
    for r in res["rows"]:
        secs = [f["seconds"] for f in r["frames"]]
        secs[0] += r["setup_s"]
        ax.plot([f["frame"] for f in r["frames"]], secs, marker="o",
                label=f"{r['mode']} K={r['k']}" if r["k"] else "reference")
    ax.set_xlabel("frame")
    ax.set_ylabel("seconds (frame 0 includes set-up)")
    ax.set_yscale("log")
    ax.legend()
    ax.set_title(f"{res['scene']['name']}: seconds per frame")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", choices=["tiny", "small", "default"], default="default")
    ap.add_argument("--shards", type=int, default=4)
    ap.add_argument("--ray-cpus", type=int, default=None, help="default: --shards")
    ap.add_argument("--train-proxies", type=int, default=None, metavar="S",
                    help="also proxy mode with proxies trained from scratch, S steps each")
    add_render_flags(ap, RESULTS)
    args = smoke(ap.parse_args(argv), size="tiny", shards=2, width=16, spp=1, bounces=1,
                 shadow_rays=1)
    scene = make_demo("windy", args.size)  # the reference renders it in memory
    stored = open_scene(f"windy:{args.size}")  # shards: metadata, as the service does
    start_ray(args.ray_cpus or args.shards)
    try:
        res = {"size": args.size, "shards": args.shards, "scene": scene.summary(),
               "moving": len(scene.animation.instances), "machine": machine(args.ray_cpus
                                                                            or args.shards)}
        rows, ref = [], None
        configs = [(0, "exact", None), (args.shards, "exact", None),
                   (args.shards, "proxy", None)]
        if args.train_proxies:
            configs.append((args.shards, "proxy", args.train_proxies))
        for k, mode, budget in configs:
            s = render_settings(args, shards=k, mode=mode)
            if k == 0:
                res["settings"] = s.model_dump()
            with tempfile.TemporaryDirectory(prefix="nprt-bench-proxies-") as fresh:
                if budget:
                    s = s.model_copy(update={"proxy": ProxySettings(width=16, steps=budget)})
                row, images = run_config(stored if k else scene, s,
                                         Path(fresh) if budget else None)
            if k == 0:
                ref = images
            elif mode == "exact":
                row["max_rel_error_vs_reference"] = max(
                    float(np.abs(images[f] - ref[f]).max() / np.abs(ref[f]).max())
                    for f in ref)
            rows.append(row)
            print(f"{row['mode']} K={k}: first {row['first_frame_s']:.2f} s, later "
                  f"{row['later_frame_s_mean']:.2f} s", flush=True)
        res["rows"] = rows
        res["machine"]["load_average_after"] = os.getloadavg()
    finally:
        ray.shutdown()
    res["train_proxies"] = args.train_proxies
    res["file"] = f"bench_frames_{args.size}.json"
    finish(res, args.out / res["file"], plot=plot, markdown=markdown, section="bench_frames",
           intro="## Animated frames\n\n![]({png})\n\n", update_readme=not args.no_readme)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
