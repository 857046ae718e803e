"""Setup cost with many instances: load, partition, instance table + top-level BVH, the
world's pickle round trip and K shards made ready, for N instances of one small mesh.

    python -m bench.render.bench_setup --instances 100000 --format npz
    python -m bench.render.bench_setup --instances 100000 --format inline   # one JSON object each

Each measurement runs in a fresh interpreter (its peak RSS is the setup's), after a
warm-up on a small scene so numba's compile/cache load is not counted. Shards are built
in-process one after another; `critical_path_s` counts the slowest one once, as K shard
processes would run in parallel, `sequential_s` counts them all. Target (issue 9):
100k instances ready in <= 5 s.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import RESULTS, child_env, finish, smoke

WARMUP_INSTANCES = 1000
TARGET_S = 5.0
STEPS = ("load", "partition", "world", "pickle", "unpickle", "shard", "surface")


def small_mesh() -> tuple[list, list]:
    """An octahedron: vertices (6, 3), faces (8, 3), as lists for JSON."""
    v = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
    f = [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
    return v, f


def instance_arrays(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """mesh (n,) int32 (all 0) and transforms (n, 4, 4) float64: random yaw, scale and
    position in a cube holding about one instance per 8 m^3, deterministic from seed."""
    rng = np.random.default_rng(seed)
    half = max(2.0, (8.0 * n) ** (1.0 / 3.0) / 2.0)
    yaw = rng.uniform(0.0, 2.0 * np.pi, n)
    scale = rng.uniform(0.3, 1.0, n)
    c, s = np.cos(yaw) * scale, np.sin(yaw) * scale
    xf = np.zeros((n, 4, 4))
    xf[:, 0, 0], xf[:, 0, 2], xf[:, 1, 1], xf[:, 2, 0], xf[:, 2, 2] = c, s, scale, -s, c
    xf[:, :3, 3] = rng.uniform(-half, half, (n, 3))
    xf[:, 3, 3] = 1.0
    return np.zeros(n, np.int32), xf


def write_scene(folder: Path, n: int, seed: int = 0, form: str = "npz") -> Path:
    """scene.json (mesh inline) with its n instances in instances.npz (form "npz") or
    listed in the JSON (form "inline", which every version of the loader reads)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    mesh, xf = instance_arrays(n, seed)
    if form == "npz":
        np.savez(folder / "instances.npz", mesh=mesh, transform=xf)
        instances = {"file": "instances.npz"}
    elif form == "inline":
        instances = [{"mesh": 0, "transform": t} for t in xf.tolist()]
    else:
        raise ValueError(f"form must be 'npz' or 'inline', got {form!r}")
    v, f = small_mesh()
    half = float(np.abs(xf[:, :3, 3]).max()) + 1.0
    doc = {"version": 1, "name": f"setup-{n}", "meshes": [{"name": "octa", "vertices": v,
                                                           "faces": f}],
           "instances": instances,
           "lights": {"directionals": [{"direction": [0.3, -1.0, 0.2],
                                        "irradiance": [3.0, 3.0, 3.0]}]},
           "camera": {"eye": [0.0, half, 3.0 * half], "target": [0.0, 0.0, 0.0]}}
    path = folder / "scene.json"
    path.write_text(json.dumps(doc))
    return path


def _rss_mb() -> float:
    """Resident set size now, MiB (Linux)."""
    return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def measure(path: Path, k: int = 2) -> dict:
    """Time each setup step once on the scene at path (this process); seconds per step,
    the world's pickle bytes, and RSS before and at peak (MiB)."""
    import pickle
    import resource

    from nprt.scene.io import load_scene
    from nprt.scene.partition import partition
    from nprt.workers.runtime.protocol import ShardConfig
    from nprt.workers.settings import RenderSettings
    from nprt.workers.wavefront.shard import Shard
    from nprt.workers.wavefront.surface import SurfaceTables
    from nprt.workers.wavefront.world import ShardWorld

    rss0 = _rss_mb()
    t = dict.fromkeys(STEPS, 0.0)
    per_shard = []

    def step(name, fn, *args):
        t0 = time.perf_counter()
        out = fn(*args)
        dt = time.perf_counter() - t0
        t[name] += dt
        return out, dt

    scene, _ = step("load", load_scene, path)
    part, _ = step("partition", partition, scene, k)
    world, _ = step("world", ShardWorld.build, scene, np.asarray(part.instance_shard))
    blob, _ = step("pickle", pickle.dumps, world, 5)
    settings = RenderSettings(shards=k)
    for sid in range(k):
        w, a = step("unpickle", pickle.loads, blob)
        meshes = {m: scene.meshes[m] for m in part.shard_meshes[sid]}
        shard, b = step("shard", Shard, ShardConfig(sid, k, settings), w, meshes, {}, None)
        # What the first shade call builds (before issue 9: where the sum order was probed).
        _, c = step("surface", SurfaceTables, meshes, w.materials, w.table)
        per_shard.append(a + b + c)
    before_shards = t["load"] + t["partition"] + t["world"] + t["pickle"]
    return {"instances": len(scene.instances), "k": k,
            "steps_s": {s: round(v, 4) for s, v in t.items()},
            "per_shard_s": [round(x, 4) for x in per_shard],
            "critical_path_s": round(before_shards + max(per_shard), 4),
            "sequential_s": round(sum(t.values()), 4),
            "world_pickle_mb": round(len(blob) / 2**20, 2),
            "rss_before_mb": round(rss0, 1),
            "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)}


def _measure_main(path: str, k: int, warmup: str | None) -> None:
    """The subprocess: warm up (compile or load numba's cache), then measure; JSON out."""
    t0 = time.perf_counter()
    if warmup:
        measure(Path(warmup), k)
    warm_s = time.perf_counter() - t0
    res = measure(Path(path), k)
    res["warmup_s"] = round(warm_s, 3)
    sys.stdout.write(json.dumps(res) + "\n")


def run(n: int = 100_000, k: int = 2, seed: int = 0, form: str = "npz",
        warmup: bool = True) -> dict:
    """Write the scene to a temporary folder and measure it in a fresh interpreter that
    imports this checkout (PYTHONPATH = the repository root)."""
    root = Path(__file__).resolve().parents[2]
    with tempfile.TemporaryDirectory(prefix="nprt-setup-") as tmp:
        path = write_scene(Path(tmp) / "big", n, seed, form)
        cmd = [sys.executable, "-m", "bench.render.bench_setup", "--measure", str(path),
               "--k", str(k)]
        if warmup:
            cmd += ["--warmup", str(write_scene(Path(tmp) / "warm", WARMUP_INSTANCES, seed + 1,
                                                form))]
        out = subprocess.run(cmd, env=child_env(), cwd=root, capture_output=True, text=True)
        if out.returncode != 0:
            raise RuntimeError(f"measurement failed ({out.returncode}):\n{out.stderr[-4000:]}")
        res = json.loads(out.stdout.strip().splitlines()[-1])
    res.update(form=form, seed=seed, target_s=TARGET_S,
               met=res["critical_path_s"] <= TARGET_S,
               machine={"platform": platform.platform(), "python": platform.python_version(),
                        "cpus": os.cpu_count(), "load_average_before": os.getloadavg()})
    return res


def table(rows: list[dict], labels: list[str]) -> str:
    """A markdown table, one column per result."""
    head = "| step (s) | " + " | ".join(labels) + " |"
    lines = [head, "|---|" + "---:|" * len(rows)]
    for s in STEPS:
        lines.append(f"| {s} | " + " | ".join(f"{r['steps_s'][s]:.3f}" for r in rows) + " |")
    for key, fmt in (("critical_path_s", "{:.3f}"), ("sequential_s", "{:.3f}"),
                     ("world_pickle_mb", "{:.1f}"), ("peak_rss_mb", "{:.0f}"),
                     ("warmup_s", "{:.2f}")):
        lines.append(f"| {key} | " + " | ".join(fmt.format(r[key]) for r in rows) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--instances", type=int, default=100_000)
    ap.add_argument("--k", type=int, default=2, help="shards")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--format", choices=("npz", "inline"), default="npz")
    ap.add_argument("--label", default="", help="added to the results file name")
    ap.add_argument("--measure", help=argparse.SUPPRESS)
    ap.add_argument("--warmup", help=argparse.SUPPRESS)
    ap.add_argument("--smoke", action="store_true", help="200 instances, for the CI smoke test")
    args = smoke(ap.parse_args(argv), instances=200)
    if args.measure:
        _measure_main(args.measure, args.k, args.warmup)
        return 0
    res = run(args.instances, args.k, args.seed, args.format)
    label = "_".join(x for x in (args.format, str(args.instances), args.label) if x)
    out = RESULTS / f"bench_setup_{label}.json"
    finish(res, out, markdown=lambda r: table([r], [label]))
    print(f"critical path {res['critical_path_s']:.2f} s (target {TARGET_S} s: "
          f"{'met' if res['met'] else 'NOT met'})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
