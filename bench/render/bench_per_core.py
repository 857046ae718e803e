"""Samples per CPU second of nprt's single-process reference renderer and of Mitsuba 3
(`scalar_rgb`, path integrator) on the same scenes, one thread each, with 4 and with 1
shadow ray per hit (Mitsuba samples one emitter per bounce whatever S is).

    python -m bench.render.bench_per_core            # the table in bench/README.md
    python -m bench.render.bench_per_core --smoke    # a tiny scene, for CI

The scenes are exported with `nprt.scene.mitsuba.to_mitsuba`: the same meshes, instances,
camera, lights and bounces (nprt's B is Mitsuba's max_depth B + 1); nprt's sky becomes a
1024-row lat-long envmap. Times are process CPU seconds (`time.process_time`) of one
render after a warm-up (numba's kernels loaded, Embree's BVHs built; Mitsuba's scene
loaded), the median of alternating repetitions; each renderer runs on one thread
(drjit's pool set to one thread; nprt's kernels are single-threaded).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import trimesh

from bench.common import BENCH_README, RESULTS, replace_section
from nprt.scene.demos import make_demo
from nprt.scene.demos._common import ground, placement, sky, sun_panel
from nprt.scene.demos.family import family_meshes
from nprt.scene.model import Camera, Material, Scene
from nprt.scene.model import Instances as InstanceArrays

SECTION = "bench_per_core"
# Targets of issue 23: nprt's samples/s over Mitsuba's at S = 1 and S = 4.
TARGETS = {1: 1.0, 4: 0.5}


def foliage_scene(trees: int = 16, rocks: int = 7, seed: int = 0) -> Scene:
    """Not a demo: two foliage meshes of the test family (leaf quads around a trunk) as
    `trees` interpenetrating trees, `rocks` displaced spheres, a ground slab, sun and sky."""
    rng = np.random.default_rng([seed, 23])
    leafy, sparse = family_meshes("default", seed)[:2]
    ico = trimesh.creation.icosphere(subdivisions=4)
    v = np.asarray(ico.vertices) * (1 + 0.1 * np.sin(3 * np.asarray(ico.vertices)).sum(1))[:, None]
    rock = type(leafy)("rock", (v * [0.9, 0.55, 0.8] + [0, 0.3, 0]).astype(np.float32),
                       np.asarray(ico.faces, np.uint32), material=2)
    meshes = (ground(25.0, material=0), leafy, sparse, rock)
    kinds = np.r_[np.arange(trees) % 2 + 1, np.full(rocks, 3)]
    n, half = len(kinds), 6.0
    pos = np.column_stack([rng.uniform(-half, half, n), np.zeros(n), rng.uniform(-half, half, n)])
    s = np.where(kinds == 3, rng.uniform(0.5, 0.9, n), rng.uniform(0.9, 1.3, n))
    xf = placement(rng.uniform(0, 2 * np.pi, n), np.repeat(s[:, None], 3, 1), pos)
    return Scene(
        meshes=meshes,
        instances=InstanceArrays(np.r_[0, kinds], np.concatenate([np.eye(4)[None], xf])),
        materials=(Material("dirt", (0.30, 0.24, 0.16)), Material("leaf", (0.20, 0.42, 0.10)),
                   Material("stone", (0.50, 0.48, 0.45))),
        quad_lights=(sun_panel((0.4 * half, 0.3 * half), 30.0, 8.0, 3.0),),
        environment=sky(0.8),
        camera=Camera(eye=(0.0, 4.5, half + 8.0), target=(0.0, 1.6, 0.0), fov_deg=50.0),
        name="foliage")


def scenes(smoke: bool) -> dict[str, Scene]:
    if smoke:
        return {"forest-tiny": make_demo("forest", "tiny")}
    return {"foliage": foliage_scene(), "forest-small": make_demo("forest", "small"),
            "sculpture-small": make_demo("sculpture", "small")}


def warm_embree(renderer) -> None:
    """One query per base mesh, so Embree's lazy BVH builds happen before any timing."""
    o = np.zeros((1, 3), np.float32)
    d = np.array([[0.0, 0.0, 1.0]], np.float32)
    for mesh_geometry in renderer.geometry.geometry.values():
        mesh_geometry.intersect_closest(o, d, np.full(1, np.inf, np.float32))
        mesh_geometry.intersect_occluded(o, d, np.full(1, np.inf, np.float32))


class NprtRun:
    """The reference renderer (shards = 0), warm, for one scene and S."""

    def __init__(self, scene: Scene, width: int, height: int, spp: int, bounces: int, s: int):
        from nprt.workers.settings import RenderSettings
        from nprt.workers.wavefront.reference import ReferenceRenderer

        self.scene = scene
        self.settings = RenderSettings(width=width, height=height, spp=spp, bounces=bounces,
                                       shadow_rays=s, shards=0)
        self.renderer = ReferenceRenderer(scene, self.settings)  # compiles / warms
        warm_embree(self.renderer)

    def __call__(self, rep: int) -> float:
        from nprt.workers.render import render

        t0 = time.process_time()
        render(self.scene, self.settings.model_copy(update={"seed": rep}),
               renderer=self.renderer)
        return time.process_time() - t0


class MitsubaRun:
    """Mitsuba 3 scalar_rgb on one thread, scene loaded (and its BVH built) up front."""

    def __init__(self, scene: Scene, width: int, height: int, spp: int, bounces: int):
        import drjit as dr

        from nprt.scene.mitsuba import _mi, to_mitsuba

        self.mi = _mi()
        dr.set_thread_count(1)
        self.spp = spp
        self.scene = self.mi.load_dict(to_mitsuba(scene, width=width, height=height, spp=spp,
                                                  bounces=bounces))
        self.mi.render(self.scene, spp=1)

    def __call__(self, rep: int) -> float:
        t0 = time.process_time()
        self.mi.render(self.scene, spp=self.spp, seed=rep)
        return time.process_time() - t0


def bench_scene(scene: Scene, args) -> dict:
    w, h, spp, b = args.width, args.height, args.spp, args.bounces
    runs = {"mitsuba": MitsubaRun(scene, w, h, spp, b)}
    for s in args.shadow_rays:
        runs[f"nprt_s{s}"] = NprtRun(scene, w, h, spp, b, s)
    times = {k: [] for k in runs}
    for rep in range(args.repeat):  # alternating, so a load spike hits every renderer
        for k, run in runs.items():
            times[k].append(run(rep + 1))
    samples = w * h * spp
    row = {"scene": scene.summary(), "samples": samples, "cpu_s": times}
    row["samples_per_s"] = {k: samples / statistics.median(v) for k, v in times.items()}
    row["ratio"] = {s: row["samples_per_s"][f"nprt_s{s}"] / row["samples_per_s"]["mitsuba"]
                    for s in args.shadow_rays}
    return row


def markdown(res: dict) -> str:
    m = res["meta"]
    lines = [f"{m['width']}x{m['height']}, {m['spp']} spp, {m['bounces']} bounces, median of "
             f"{m['repeat']} alternating runs, process CPU seconds; {m['machine']}.", "",
             "| scene | instanced triangles | Mitsuba 3 ksamples/s | S | nprt ksamples/s | "
             "nprt / Mitsuba | target |", "| --- | ---: | ---: | ---: | ---: | ---: | --- |"]
    for name, r in res["scenes"].items():
        mi_rate = r["samples_per_s"]["mitsuba"]
        for s, ratio in r["ratio"].items():
            target = TARGETS.get(int(s))
            verdict = "" if target is None else (
                f">= {target}: {'met' if ratio >= target else 'NOT met'}")
            lines.append(f"| {name} | {r['scene']['instanced_triangles']:,} | "
                         f"{mi_rate / 1e3:.0f} | {s} | "
                         f"{r['samples_per_s'][f'nprt_s{s}'] / 1e3:.0f} | {ratio:.2f} | "
                         f"{verdict} |")
    return "\n".join(lines)


INTRO = ("## Per-core speed against Mitsuba 3 (`bench_per_core.py`)\n\n"
         "`python -m bench.render.bench_per_core` renders the same scenes with nprt's "
         "reference renderer and Mitsuba 3 (`scalar_rgb`, path integrator), each on one "
         "thread, exported by `nprt.scene.mitsuba` (`tests/scene/test_mitsuba.py` checks "
         "that the images agree within noise). *foliage* is not a demo: 16 trees of the "
         "test family's two leaf-cloud meshes, 7 rocks and a ground slab, sun and sky. "
         "Results: `{json}`.\n\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--smoke", action="store_true", help="tiny scene and image, one run")
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--bounces", type=int, default=5)
    ap.add_argument("--shadow-rays", type=int, nargs="+", default=[4, 1])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    if args.smoke:
        args.width, args.height, args.spp, args.repeat = 16, 12, 1, 1
    res = {"meta": {"width": args.width, "height": args.height, "spp": args.spp,
                    "bounces": args.bounces, "repeat": args.repeat,
                    "machine": f"{platform.machine()}, {platform.python_implementation()} "
                               f"{platform.python_version()}, one thread each",
                    "load_average_before": os.getloadavg()},
           "scenes": {}}
    for name, scene in scenes(args.smoke).items():
        res["scenes"][name] = bench_scene(scene, args)
        print(name, json.dumps(res["scenes"][name]["ratio"]), flush=True)
    write_results(res, args.out, SECTION, args.smoke, INTRO, markdown(res))
    return 0


def write_results(res: dict, out: Path, stem: str, smoke: bool, intro: str,
                  table: str) -> None:
    """JSON at out/<stem>[_smoke].json, the table printed, and, for a full run written to
    bench/results, the `<!-- stem:begin/end -->` section of bench/README.md replaced by
    intro (`{json}`: the file) and the table."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / (f"{stem}_smoke.json" if smoke else f"{stem}.json")
    path.write_text(json.dumps(res, indent=1))
    print(table)
    beside = out.resolve() == (BENCH_README.parent / "results").resolve()
    if beside and not smoke:
        replace_section(BENCH_README, f"<!-- {stem}:begin -->", f"<!-- {stem}:end -->",
                        intro.replace("{json}", str(path.relative_to(BENCH_README.parent)))
                        + table)


if __name__ == "__main__":
    sys.exit(main())
