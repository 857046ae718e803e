"""The reference renderer's traversal against raw single-threaded Embree on the same rays:
every ray the renderer's two-level traversal (`LocalGeometry`: top-level boxes, then each
ray's boxes nearest first, moved into the instance's space and traced through Embree's C
API from a compiled loop) answers is recorded and replayed
through one `EmbreeScene.run` on the scene baked into world space (every instance's
triangles in one mesh, robust mode as the renderer).

    python -m bench.render.bench_reference             # the table in bench/README.md
    python -m bench.render.bench_reference --smoke     # a tiny scene, for CI

Rows: *closest* (camera and bounce rays, against raw closest hit), *shadow* (against raw
occlusion), *traversal* (both), and *end to end* (the whole render's CPU, generation and
shading included, against raw Embree on all its rays). Ratio = renderer rays/s over raw
rays/s. Times are CPU seconds of this thread (`time.thread_time`); the renderer is warmed
up first (numba's kernels, Embree's lazy BVH builds) and the raw replay is the best of
RAW_REPEATS, its first repeat absorbing the BVH build.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from embreex import mesh_construction, rtcore_scene

from bench.render.bench_per_core import foliage_scene, warm_embree, write_results
from nprt.scene.demos import make_demo
from nprt.scene.model import Scene
from nprt.workers.render import render
from nprt.workers.settings import RenderSettings
from nprt.workers.traversal.geometry import EMBREE_DTYPE
from nprt.workers.wavefront.reference import ReferenceRenderer

RESULTS = Path(os.environ.get("NPRT_BENCH_RESULTS")
               or Path(__file__).resolve().parents[1] / "results")
SECTION = "bench_reference"
TARGET_RATIO = 0.8  # issue 23: the reference's traversal at >= 0.8x raw Embree
RAW_REPEATS = 3
clock = time.thread_time


class TimedGeometry:
    """A LocalGeometry that records the rays of each query (origin, direction, tmax as
    passed) and the CPU seconds spent answering them, by query."""

    def __init__(self, inner):
        self.inner = inner
        self.seconds = {"closest": 0.0, "shadow": 0.0}
        self.rays = {"closest": [], "shadow": []}

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def intersect_closest(self, origin, direction, tmax, hit_inst=None, hit_prim=None):
        self.rays["closest"].append((origin.astype(EMBREE_DTYPE), direction.copy(),
                                     tmax.copy()))
        t0 = clock()
        out = self.inner.intersect_closest(origin, direction, tmax, hit_inst, hit_prim)
        self.seconds["closest"] += clock() - t0
        return out

    def intersect_occluded(self, origin, direction, tmax):
        self.rays["shadow"].append((origin.astype(EMBREE_DTYPE), direction.copy(),
                                    tmax.copy()))
        t0 = clock()
        out = self.inner.intersect_occluded(origin, direction, tmax)
        self.seconds["shadow"] += clock() - t0
        return out

    def arrays(self, kind: str):
        """origin, direction (n, 3) float32 and tmax (n,) float32 of every `kind` query."""
        parts = self.rays[kind]
        if not parts:
            z = np.zeros((0, 3), np.float32)
            return z, z, np.zeros(0, np.float32)
        return tuple(np.ascontiguousarray(np.concatenate(x)) for x in zip(*parts, strict=True))


def flatten_to_world(scene: Scene) -> tuple[rtcore_scene.EmbreeScene, int]:
    """One Embree scene holding every instance's triangles in world space (vertices moved
    in float64, then float32), robust mode as the renderer's."""
    verts, faces, offset = [], [], 0
    for inst in scene.instances:
        mesh = scene.meshes[inst.mesh]
        xf = np.asarray(inst.transform, np.float64)
        verts.append(mesh.vertices.astype(np.float64) @ xf[:3, :3].T + xf[:3, 3])
        faces.append(mesh.faces.astype(np.int64) + offset)
        offset += len(mesh.vertices)
    emb = rtcore_scene.EmbreeScene(robust=True)
    tris = np.concatenate(faces)
    mesh_construction.TriangleMesh(emb, np.concatenate(verts).astype(EMBREE_DTYPE),
                                   tris.astype(np.int32))
    return emb, len(tris)


def time_raw(emb, o, d, tmax, query: str) -> float:
    """Best-of-RAW_REPEATS CPU seconds of one embreex call on all rays (a fresh tmax each
    time: embreex writes tfar into it)."""
    best = np.inf
    for _ in range(RAW_REPEATS):
        dists = np.array(tmax, EMBREE_DTYPE)
        t0 = clock()
        if query == "closest":
            emb.run(o, d, dists=dists, output=1)
        else:
            emb.run(o, d, dists=dists, query="OCCLUDED")
        best = min(best, clock() - t0)
    return best


def warm_walks(geometry) -> None:
    """One query of each kind through the renderer's own geometry. The renderer's warm-up
    pass (4x4 pixels) may cast no shadow ray, and then loading the occlusion walk from
    numba's cache (about 10 ms, foliage) fell inside the timed shadow queries."""
    o = np.zeros((1, 3))
    d = np.array([[0.0, 0.0, 1.0]], EMBREE_DTYPE)
    tmax = np.full(1, np.inf, EMBREE_DTYPE)
    geometry.intersect_closest(o, d, tmax, np.full(1, -1, np.int32), np.full(1, -1, np.int32))
    geometry.intersect_occluded(o, d, tmax)


def bench_scene(scene: Scene, settings: RenderSettings) -> dict:
    renderer = ReferenceRenderer(scene, settings)  # warms the kernels
    warm_embree(renderer)
    warm_walks(renderer.geometry)
    timed = renderer.geometry = TimedGeometry(renderer.geometry)
    c0 = clock()
    render(scene, settings, renderer=renderer)
    cpu = clock() - c0
    emb, n_tris = flatten_to_world(scene)
    rows, raw_all = {}, 0.0
    for kind, query in (("closest", "closest"), ("shadow", "occluded")):
        o, d, tmax = timed.arrays(kind)
        if len(o) == 0:
            continue
        raw = time_raw(emb, o, d, tmax, query)
        raw_all += raw
        rows[kind] = {"rays": len(o), "renderer_s": timed.seconds[kind], "raw_s": raw}
    rows["traversal"] = {"rays": sum(r["rays"] for r in rows.values()),
                         "renderer_s": sum(timed.seconds.values()), "raw_s": raw_all}
    rows["end to end"] = {**rows["traversal"], "renderer_s": cpu}
    for r in rows.values():
        r["ratio"] = r["raw_s"] / r["renderer_s"]  # rays/s over raw rays/s, same rays
    return {"scene": scene.summary(), "world_triangles": n_tris, "rows": rows}


def markdown(res: dict) -> str:
    m = res["meta"]
    lines = [f"{m['width']}x{m['height']}, {m['spp']} spp, {m['bounces']} bounces, "
             f"{m['shadow_rays']} shadow rays; rates in million rays per CPU second; "
             f"{m['machine']}.", "",
             "| scene | queries | rays | renderer Mrays/s | raw Embree Mrays/s | ratio | target |",
             "| --- | --- | ---: | ---: | ---: | ---: | --- |"]
    for name, r in res["scenes"].items():
        for kind, v in r["rows"].items():
            verdict = "met" if v["ratio"] >= TARGET_RATIO else "NOT met"
            lines.append(f"| {name} | {kind} | {v['rays']:,} | "
                         f"{v['rays'] / v['renderer_s'] / 1e6:.3f} | "
                         f"{v['rays'] / v['raw_s'] / 1e6:.3f} | {v['ratio']:.2f} | "
                         f"{'' if kind == 'end to end' else verdict} |")
    return "\n".join(lines)


INTRO = ("## Reference renderer against raw Embree (`bench_reference.py`)\n\n"
         "`python -m bench.render.bench_reference` records every ray the reference "
         "renderer's two-level traversal answers and replays it through one raw "
         "single-threaded Embree call on the scene baked into world space. Ratio = "
         "renderer rays/s over raw rays/s on the same rays (target >= "
         f"{TARGET_RATIO} for the traversal). Results: `{{json}}`.\n\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--smoke", action="store_true", help="tiny scene and image")
    ap.add_argument("--size", choices=["tiny", "small", "default"], default="small")
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--bounces", type=int, default=5)
    ap.add_argument("--shadow-rays", type=int, default=4)
    ap.add_argument("--scenes", default="foliage,forest,city,sculpture",
                    help="comma-separated: demo names and/or 'foliage' (bench_per_core's)")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    if args.smoke:
        args.size, args.width, args.height, args.spp, args.scenes = "tiny", 32, 24, 1, "forest"
    settings = RenderSettings(width=args.width, height=args.height, spp=args.spp,
                              bounces=args.bounces, shadow_rays=args.shadow_rays)
    res = {"meta": {"size": args.size, "width": args.width, "height": args.height,
                    "spp": args.spp, "bounces": args.bounces, "shadow_rays": args.shadow_rays,
                    "machine": f"{platform.machine()}, {platform.python_implementation()} "
                               f"{platform.python_version()}, one thread",
                    "load_average_before": os.getloadavg()},
           "scenes": {}}
    for name in args.scenes.split(","):
        scene = foliage_scene() if name == "foliage" else make_demo(name, args.size)
        label = name if name == "foliage" else f"{name}-{args.size}"
        res["scenes"][label] = bench_scene(scene, settings)
        print(label, json.dumps({k: round(v["ratio"], 3)
                                 for k, v in res["scenes"][label]["rows"].items()}), flush=True)
    write_results(res, args.out, SECTION, args.smoke, INTRO, markdown(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
