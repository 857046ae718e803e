"""`python -m bench.render.bench_massive`: forest:massive (1.1 GB of base meshes) rendered exact at
K = 4 and K = 8 by drivers that hold no geometry, and its proxies trained as parallel Ray
tasks against one after another, all in one run on one local Ray.

Each render runs in its own driver process (joining this run's Ray), so its peak
resident memory (VmHWM) is the driver's alone; it is reported whole, above the driver's
own baseline (after its imports and joining Ray, before opening the scene), and beside a
bare Ray driver's (a process that imports Ray and joins it, nothing else): the floor no
Ray driver goes below, whatever the scene.
Training uses a short non-default budget (so the shipped proxies are not found) and one
width, the same for both schedules.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import RESULTS, child_env, publish, smoke, start_ray  # light: no Ray, no nprt

ROOT = Path(__file__).resolve().parents[2]


def _rss_mb() -> float:
    """Peak resident memory of this process's own address space (VmHWM, MB). Not
    ru_maxrss: Linux carries a parent's RSS at fork across exec into it, so a driver
    spawned by a parent that just generated the scene would report the parent's peak."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024  # kB
    raise RuntimeError("no VmHWM in /proc/self/status (Linux only)")


TRACING_LIBRARIES = ("numba", "llvmlite", "embreex", "onnxruntime", "trimesh", "torch")


def bare_driver(args) -> int:
    """Import Ray, join it, report the peak RSS: the floor of any Ray driver."""
    import ray

    ray.init(address=args.address, log_to_driver=False)
    Path(args.report).write_text(json.dumps({"rss_peak_mb": round(_rss_mb(), 1)}))
    ray.shutdown()
    return 0


def driver(args) -> int:
    """One render, in this process: open the scene as metadata, render, report."""
    import ray

    from nprt.scene.store import open_scene
    from nprt.workers.render import render
    from nprt.workers.settings import RenderSettings

    ray.init(address=args.address, log_to_driver=False)
    import nprt.workers.runtime.coordinator  # noqa: F401 (its imports count in the baseline)

    base = _rss_mb()
    meta = open_scene(args.scene)
    s = RenderSettings(width=args.width, height=args.height, spp=args.spp,
                       spp_per_pass=args.spp, bounces=args.bounces, shards=args.driver)
    t0 = time.perf_counter()
    res = render(meta, s)
    wall = time.perf_counter() - t0
    np.save(args.image, res.film.image())
    info = res.info
    Path(args.report).write_text(json.dumps({
        "k": args.driver, "wall_s": round(wall, 3), "prepare_s": info["prepare_s"],
        "rss_baseline_mb": round(base, 1), "rss_peak_mb": round(_rss_mb(), 1),
        "shard_geometry_bytes": info["shard_geometry_bytes"],
        "shard_meshes": [sh["meshes"] for sh in info["shard_stats"]],
        "shard_load_s": [sh["load_s"] for sh in info["shard_stats"]],
        "mesh_bytes": meta.mesh_bytes, "summary": meta.summary(),
        "tracing_libraries": sorted({m.split(".")[0] for m in sys.modules}
                                    & set(TRACING_LIBRARIES))}))
    ray.shutdown()
    return 0


def _child(report: Path, *flags: str) -> dict:
    """Run this module as a driver process with `flags`; returns the report it wrote."""
    cmd = [sys.executable, "-m", "bench.render.bench_massive", *flags, "--report", str(report)]
    subprocess.run(cmd, check=True, cwd=ROOT, env=child_env())
    return json.loads(report.read_text())


def _bare(address: str, tmp: Path) -> float:
    return _child(tmp / "bare.json", "--bare", "--address", address)["rss_peak_mb"]


def _render(k: int, args, address: str, tmp: Path, scene: str | None = None
            ) -> tuple[dict, np.ndarray]:
    scene = scene or args.scene
    image = tmp / f"{scene}-k{k}.npy"
    report = _child(tmp / f"{scene}-k{k}.json", "--driver", str(k), "--address", address,
                    "--image", str(image), "--scene", scene, "--width", str(args.width),
                    "--height", str(args.height), "--spp", str(args.spp),
                    "--bounces", str(args.bounces))
    return report, np.load(image)


def _train(meta, parallel: bool, args, tmp: Path) -> dict:
    from nprt.proxies.config import ProxyConfig
    from nprt.proxies.tasks import RayTrainer

    trees = [i for i, m in enumerate(meta.meshes) if m.n_faces > 1000]
    trainer = RayTrainer(meta.source, tmp / ("par" if parallel else "seq"), parallel=parallel,
                         names={i: m.name for i, m in enumerate(meta.meshes)})
    failed = trainer(trees, ProxyConfig(steps=args.train_steps), (args.train_width,), 0.0)
    return {"parallel": parallel, "wall_s": round(trainer.wall_s, 2), "meshes": len(trees),
            "failed": len(failed), "per_mesh_s": [r["seconds"] for r in trainer.progress]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.render.bench_massive", description=__doc__)
    ap.add_argument("--scene", default="forest:massive")
    ap.add_argument("--small-scene", default="forest:default",
                    help="the same driver on a small scene: its peak RSS against the "
                         "massive one's shows what grows with mesh bytes")
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--height", type=int, default=48)
    ap.add_argument("--spp", type=int, default=1)
    ap.add_argument("--bounces", type=int, default=2)
    ap.add_argument("--train-steps", type=int, default=1000)
    ap.add_argument("--train-width", type=int, default=16)
    ap.add_argument("--ray-cpus", type=int, default=8,
                    help="Ray's CPUs for the renders (K = 8 wants 8)")
    ap.add_argument("--ks", type=int, nargs=2, default=[4, 8],
                    help="the two shard counts rendered (their images must be equal)")
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_massive.json")
    ap.add_argument("--no-readme", action="store_true")
    ap.add_argument("--smoke", action="store_true", help="tiny scene, for the CI smoke test")
    ap.add_argument("--driver", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--bare", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--address", help=argparse.SUPPRESS)
    ap.add_argument("--image", help=argparse.SUPPRESS)
    ap.add_argument("--report", help=argparse.SUPPRESS)
    args = smoke(ap.parse_args(argv), scene="forest:small", small_scene="forest:tiny", width=8,
                 height=6, bounces=1, train_steps=20, train_width=8, ray_cpus=2, ks=[1, 2])
    if args.bare:
        return bare_driver(args)
    if args.driver:
        return driver(args)

    import ray

    from nprt.scene.store import open_scene

    load_before = os.getloadavg()
    t0 = time.perf_counter()
    meta = open_scene(args.scene)  # generated and written once, if not cached yet
    open_s = time.perf_counter() - t0
    with tempfile.TemporaryDirectory(prefix="bench-massive-") as tmp:
        tmp = Path(tmp)
        start_ray(args.ray_cpus)  # or the cluster RAY_ADDRESS names (the smoke test's)
        try:
            address = ray.get_runtime_context().gcs_address
            bare_mb = _bare(address, tmp)
            renders = {k: _render(k, args, address, tmp) for k in args.ks}
            small, _ = _render(args.ks[0], args, address, tmp, args.small_scene)
        finally:
            ray.shutdown()
        # Training on as many Ray CPUs as real cores: each task trains one thread, so
        # more tasks than cores would only share them.
        start_ray(os.cpu_count())
        try:
            training = [_train(meta, True, args, tmp), _train(meta, False, args, tmp)]
        finally:
            ray.shutdown()
    mesh_bytes = meta.mesh_bytes
    rows = {}
    for k, (rep, _) in renders.items():
        rows[k] = {**rep, "rss_peak_share": round(rep["rss_peak_mb"] * 2**20 / mesh_bytes, 4),
                   "rss_scene_share": round((rep["rss_peak_mb"] - rep["rss_baseline_mb"])
                                            * 2**20 / mesh_bytes, 4),
                   "rss_above_bare_share": round((rep["rss_peak_mb"] - bare_mb)
                                                 * 2**20 / mesh_bytes, 4),
                   "max_shard_share": round(max(rep["shard_geometry_bytes"]) / mesh_bytes, 4)}
    res = {"scene": args.scene, "summary": meta.summary(), "open_s": round(open_s, 2),
           "bare_ray_driver_mb": bare_mb,
           "small_scene": {"scene": args.small_scene, "k": args.ks[0],
                           "mesh_bytes": small["mesh_bytes"],
                           "rss_peak_mb": small["rss_peak_mb"]},
           "bare_ray_driver_share": round(bare_mb * 2**20 / mesh_bytes, 4),
           "settings": {k: getattr(args, k) for k in ("width", "height", "spp", "bounces",
                                                      "train_steps", "train_width",
                                                      "ray_cpus")},
           "renders": rows,
           "k4_equals_k8": bool(np.array_equal(*(renders[k][1] for k in args.ks))),
           "training": training,
           "train_speedup": round(training[1]["wall_s"] / training[0]["wall_s"], 3),
           "load_average_before": load_before, "load_average_after": os.getloadavg(),
           "cpus": os.cpu_count()}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=1))
    table = markdown(res)
    print(table)
    if not args.no_readme:
        publish("bench_massive", table, args.out)
    return 0


def markdown(res: dict) -> str:
    s, mb = res["summary"], res["summary"]["mesh_bytes"]
    lines = [
        "### Massive scene: the driver holds no geometry",
        "",
        f"`python -m bench.render.bench_massive` (`bench/results/bench_massive.json`): "
        f"`{res['scene']}`, {mb / 1e9:.2f} GB of base meshes ({s['base_meshes']} meshes), "
        f"{s['instances']:,} instances, {s['instanced_triangles']:.2e} instanced triangles; "
        f"{res['settings']['width']}x{res['settings']['height']}, {res['settings']['spp']} spp, "
        f"{res['settings']['bounces']} bounces, exact; {res['cpus']} cores, load average "
        f"{res['load_average_before'][0]:.1f} before and {res['load_average_after'][0]:.1f} "
        f"after.",
        "",
        f"A bare Ray driver (import Ray, join, nothing else) peaks at "
        f"**{res['bare_ray_driver_mb']:.0f} MB, {100 * res['bare_ray_driver_share']:.1f} %** "
        f"of the mesh bytes: the floor of any driver on this Ray. The same K = 4 driver "
        f"on `{res['small_scene']['scene']}` "
        f"({res['small_scene']['mesh_bytes'] / 1e6:.1f} MB of meshes, "
        f"{mb / res['small_scene']['mesh_bytes']:.0f}x fewer) peaks at "
        f"**{res['small_scene']['rss_peak_mb']:.0f} MB**.",
        "",
        "| K | driver peak RSS MB | share of mesh bytes | above a bare Ray driver | "
        "above the driver's baseline | tracing libraries imported | "
        "largest shard geometry | share | shard load s (max) | prepare s | render s |",
        "| ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for k, r in res["renders"].items():
        lines.append(
            f"| {k} | {r['rss_peak_mb']:.0f} | {100 * r['rss_peak_share']:.1f} % | "
            f"{100 * r['rss_above_bare_share']:.1f} % | {100 * r['rss_scene_share']:.1f} % | "
            f"{', '.join(r['tracing_libraries']) or 'none'} | "
            f"{max(r['shard_geometry_bytes']) / 1e6:.0f} MB"
            f" | {100 * r['max_shard_share']:.1f} % | {max(r['shard_load_s']):.1f} | "
            f"{r['prepare_s']:.1f} | {r['wall_s']:.1f} |")
    par, seq = res["training"]
    lines += [
        "",
        f"K = 4 and K = 8 exact images identical: **{res['k4_equals_k8']}**.",
        "",
        f"Proxy training of the {par['meshes']} tree meshes (width "
        f"{res['settings']['train_width']}, {res['settings']['train_steps']} steps "
        f"each, one Ray task per mesh): "
        f"**{par['wall_s']:.1f} s** in parallel against **{seq['wall_s']:.1f} s** one after "
        f"another, {res['train_speedup']:.2f}x ({par['failed'] + seq['failed']} failed), "
        f"on a Ray with one CPU per core ({res['cpus']}), so at most {res['cpus']} tasks "
        f"at once.",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
