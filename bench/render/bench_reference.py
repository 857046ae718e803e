"""Rays per second of the single-process reference renderer on the demo scenes, by ray
kind, next to raw single-threaded Embree on the same rays against the world-space
flattened scene (every instance baked into one mesh).

    python -m bench.render.bench_reference --size small --width 128 --spp 4

Per kind, "renderer" time is what the reference renderer spends resolving those rays:
`resolve_closest` (two-level Embree + quad lights) for primary and secondary rays,
`unoccluded` for shadow rays; these are the 'intersect' and 'shadow' phases of
RenderStats, split by kind. "Raw" replays exactly the rays the renderer traced (origin,
direction and tmax as it passed them) through `EmbreeScene.run(o, d, dists=tmax,
output=1)` on the baked world scene, and the occlusion query for shadow rays. The ratio is
renderer rays/s over raw rays/s (target >= 0.4). End to end divides all rays by the whole
render's wall time (generation and shading included) and compares with raw closest-hit on
all of them.

Times are CPU seconds of the calling thread (`time.thread_time`): everything timed runs
single-threaded, and on a shared machine CPU time is far steadier than wall time (the
JSON has the render's wall time too). Embree builds its BVHs lazily on the first query;
both sides are warmed up first so no build is timed (nor numba's first-use load of the
renderer's jitted kernels).

The instrumentation wraps two module-level functions of `nprt.workers.wavefront.reference` for the
duration of one render and restores them; nothing in workers/ is changed or slowed.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import platform
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: make the repository importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from embreex import mesh_construction, rtcore_scene  # noqa: E402

import nprt.workers.wavefront.reference as reference_module  # noqa: E402
from bench.common import replace_section  # noqa: E402
from nprt.scene.demos import DEMOS, make_demo  # noqa: E402
from nprt.scene.model import Scene  # noqa: E402
from nprt.workers.render import render  # noqa: E402
from nprt.workers.settings import RenderSettings  # noqa: E402
from nprt.workers.traversal.geometry import EMBREE_DTYPE  # noqa: E402
from nprt.workers.wavefront.batch import KIND_NAMES, SHADOW  # noqa: E402
from nprt.workers.wavefront.reference import ReferenceRenderer  # noqa: E402

log = logging.getLogger(__name__)

RESULTS = Path(__file__).resolve().parents[1] / "results"
README = Path(__file__).resolve().parents[1] / "README.md"
TARGET_RATIO = 0.4
RAW_REPEATS = 3  # best of: the machine is shared, the minimum is the least disturbed
clock = time.thread_time  # CPU seconds of this thread; see the module docstring
README_BEGIN, README_END = "<!-- bench_reference:begin -->", "<!-- bench_reference:end -->"


class RayLog:
    """Per-kind seconds and the rays (origin, direction, tmax as passed) of every query,
    plus per-kind seconds inside the slab test and inside Embree (the rest of a kind's
    time is moving rays to local space, sorting and merging hits, and the quad lights)."""

    def __init__(self):
        self.seconds = defaultdict(float)
        self.slab_s = defaultdict(float)
        self.embree_s = defaultdict(float)
        self.rays = defaultdict(list)  # kind name -> [(o (n,3) f32, d (n,3) f32, tmax (n,) f32)]
        self.kind = None  # kind being resolved right now

    def count(self, kind: str) -> int:
        return int(sum(len(o) for o, _, _ in self.rays[kind]))

    def arrays(self, kind: str):
        parts = self.rays[kind]
        if not parts:
            z = np.zeros((0, 3), np.float32)
            return z, z, np.zeros(0, np.float32)
        return tuple(np.concatenate(x) for x in zip(*parts, strict=True))

    def timed(self, fn, bucket: dict):
        """fn wrapped to add its seconds to bucket[current kind]."""
        def wrapper(*args, **kw):
            t0 = clock()
            try:
                return fn(*args, **kw)
            finally:
                bucket[self.kind] += clock() - t0
        return wrapper


@contextlib.contextmanager
def instrument_reference(renderer: ReferenceRenderer, raylog: RayLog):
    """Time and record nprt.workers.wavefront.reference's closest-hit and shadow queries by
    ray kind.

    The two module-level stage functions are swapped for timing wrappers while the
    context is open; the slab test and Embree calls are wrapped on this renderer's own
    objects only."""
    closest, shadow = reference_module.resolve_closest, reference_module.unoccluded

    def timed_closest(rays, geometry, lights):
        kinds = np.unique(rays.kind)
        raylog.kind = KIND_NAMES[int(kinds[0])] if len(kinds) == 1 else "mixed"
        copy = (rays.origin.copy(), rays.direction.copy(), rays.tmax.copy())
        t0 = clock()
        out = closest(rays, geometry, lights)
        raylog.seconds[raylog.kind] += clock() - t0
        raylog.rays[raylog.kind].append(copy)
        return out

    def timed_shadow(batch, geometry):
        raylog.kind = KIND_NAMES[SHADOW]
        copy = (batch.origin.copy(), batch.direction.copy(), batch.tmax.copy())
        t0 = clock()
        out = shadow(batch, geometry)
        raylog.seconds[raylog.kind] += clock() - t0
        raylog.rays[raylog.kind].append(copy)
        return out

    table = renderer.geometry.table
    table.box_entries = raylog.timed(table.box_entries, raylog.slab_s)
    for mesh_geometry in renderer.geometry.geometry.values():
        for name in ("intersect_closest", "intersect_occluded"):
            setattr(mesh_geometry, name,
                    raylog.timed(getattr(mesh_geometry, name), raylog.embree_s))
    reference_module.resolve_closest, reference_module.unoccluded = timed_closest, timed_shadow
    try:
        yield raylog
    finally:
        reference_module.resolve_closest, reference_module.unoccluded = closest, shadow


def flatten_to_world(scene: Scene) -> tuple[rtcore_scene.EmbreeScene, int]:
    """One Embree scene holding every instance's triangles in world space (vertices moved
    in float64, then float32), built with the renderer's flags (robust mode)."""
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
    """Best-of-RAW_REPEATS CPU seconds of one embreex call on all rays (fresh tmax each
    time: embreex writes tfar into it). The first repeat also absorbs the BVH build."""
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


def warm_up(renderer: ReferenceRenderer) -> None:
    """One query per base mesh, so Embree's lazy BVH builds happen before any timing, and
    one through the two-level path, so numba's first-use load (or compile) of the jitted
    kernels is not timed either: both are once per process, not per ray."""
    o = np.zeros((1, 3), np.float32)
    d = np.array([[0.0, 0.0, 1.0]], np.float32)
    for mesh_geometry in renderer.geometry.geometry.values():
        mesh_geometry.intersect_closest(o, d, np.full(1, np.inf, np.float32))
        mesh_geometry.intersect_occluded(o, d, np.full(1, np.inf, np.float32))
    table, every = renderer.geometry.table, np.arange(len(renderer.geometry.table))
    for instances in (every, every[:1]):  # the BVH kernel and the plain loop
        table.box_entries(o, d, np.full(1, np.inf, np.float32), instances)
    renderer.geometry.intersect_closest(o, d, np.full(1, np.inf, np.float32))
    renderer.geometry.intersect_occluded(o, d, np.full(1, np.inf, np.float32))


def bench_scene(name: str, size: str, settings: RenderSettings) -> dict:
    scene = make_demo(name, size)
    renderer = ReferenceRenderer(scene, settings)
    warm_up(renderer)
    raylog = RayLog()
    with instrument_reference(renderer, raylog):
        t0, c0 = time.perf_counter(), clock()
        result = render(scene, settings, renderer=renderer)
        wall, cpu = time.perf_counter() - t0, clock() - c0
    stats = result.stats.to_dict()
    emb, n_tris = flatten_to_world(scene)
    kinds, all_closest = {}, 0.0
    for kind in [*KIND_NAMES, "mixed"]:
        n = raylog.count(kind)
        if n == 0:
            continue
        o, d, tmax = raylog.arrays(kind)
        o = np.ascontiguousarray(o, EMBREE_DTYPE)  # float64 on the wire; raw Embree takes f32
        raw_closest = time_raw(emb, o, d, tmax, "closest")
        all_closest += raw_closest
        row = {"rays": n, "renderer_s": raylog.seconds[kind], "slab_s": raylog.slab_s[kind],
               "embree_s": raylog.embree_s[kind], "raw_closest_s": raw_closest,
               "renderer_rays_per_s": n / raylog.seconds[kind],
               "raw_closest_rays_per_s": n / raw_closest}
        if kind == KIND_NAMES[SHADOW]:
            raw_occ = time_raw(emb, o, d, tmax, "occluded")
            row.update(raw_occluded_s=raw_occ, raw_occluded_rays_per_s=n / raw_occ)
        row["ratio"] = row["renderer_rays_per_s"] / row["raw_closest_rays_per_s"]
        kinds[kind] = row
    total = sum(k["rays"] for k in kinds.values())
    return {
        "scene": scene.summary(), "world_triangles": n_tris, "kinds": kinds,
        "end_to_end": {"rays": total, "wall_s": wall, "cpu_s": cpu, "rays_per_s": total / cpu,
                       "raw_closest_s": all_closest, "raw_closest_rays_per_s": total / all_closest,
                       "ratio": all_closest / cpu},
        "phase_s": stats["phase_s"], "stats_rays": stats["rays"],
    }


def markdown_table(results: dict, meta: dict) -> str:
    lines = [
        f"Reference renderer vs raw single-threaded Embree on the same rays "
        f"(size `{meta['size']}`, {meta['width']}x{meta['height']}, {meta['spp']} spp, "
        f"{meta['tile_size']}px tiles, "
        f"{meta['bounces']} bounces, {meta['shadow_rays']} shadow rays; "
        f"{meta['machine']}). Rates in million rays per CPU second; target ratio >= "
        f"{TARGET_RATIO}.",
        "",
        "| scene | kind | rays | renderer Mrays/s | raw closest Mrays/s | ratio | "
        "raw occluded Mrays/s | slab / Embree / rest of renderer time | target |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | --- | --- |",
    ]
    for name, r in results.items():
        rows = [(k, v) for k, v in r["kinds"].items()]
        e = r["end_to_end"]
        rows.append(("end to end", {"rays": e["rays"], "renderer_rays_per_s": e["rays_per_s"],
                                    "raw_closest_rays_per_s": e["raw_closest_rays_per_s"],
                                    "ratio": e["ratio"]}))
        for kind, v in rows:
            occ = v.get("raw_occluded_rays_per_s")
            split = ""
            if "slab_s" in v:
                parts = np.array([v["slab_s"], v["embree_s"]]) / v["renderer_s"]
                split = f"{parts[0]:.0%} / {parts[1]:.0%} / {1 - parts.sum():.0%}"
            lines.append(
                f"| {name} | {kind} | {v['rays']:,} | {v['renderer_rays_per_s'] / 1e6:.3f} | "
                f"{v['raw_closest_rays_per_s'] / 1e6:.3f} | {v['ratio']:.2f} | "
                f"{'' if occ is None else f'{occ / 1e6:.3f}'} | {split} | "
                f"{'met' if v['ratio'] >= TARGET_RATIO else 'NOT met'} |")
    return "\n".join(lines)


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results)
    kinds = list(KIND_NAMES)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    x = np.arange(len(names))
    w = 0.8 / (2 * len(kinds))
    for j, kind in enumerate(kinds):
        rend = [results[n]["kinds"].get(kind, {}).get("renderer_rays_per_s", 0) / 1e6
                for n in names]
        raw = [results[n]["kinds"].get(kind, {}).get("raw_closest_rays_per_s", 0) / 1e6
               for n in names]
        colour = f"C{j}"
        axes[0].bar(x + (2 * j) * w - 0.4 + w / 2, rend, w, color=colour,
                    label=f"{kind} renderer")
        axes[0].bar(x + (2 * j + 1) * w - 0.4 + w / 2, raw, w, color=colour, alpha=0.35,
                    hatch="//", label=f"{kind} raw Embree")
        ratio = [results[n]["kinds"].get(kind, {}).get("ratio", 0) for n in names]
        axes[1].bar(x + j * (0.8 / len(kinds)) - 0.4 + 0.4 / len(kinds), ratio,
                    0.8 / len(kinds), color=f"C{j}", label=kind)
    axes[1].axhline(TARGET_RATIO, color="k", ls="--", lw=1, label=f"target {TARGET_RATIO}")
    axes[0].set(xticks=x, xticklabels=names, ylabel="million rays per CPU second",
                title="throughput by ray kind")
    axes[1].set(xticks=x, xticklabels=names, ylabel="renderer / raw",
                title="ratio to raw Embree (closest hit)")
    axes[0].legend(fontsize=7)
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_readme_section(out: Path) -> None:
    """Replace this bench's section of bench/README.md with one table per results file
    (bench_reference_*.json in `out`), leaving other sections alone."""
    tables, met, rows = [], 0, 0
    for path in sorted(out.glob("bench_reference_*.json")):
        data = json.loads(path.read_text())
        for r in data["results"].values():
            ratios = [v["ratio"] for v in r["kinds"].values()] + [r["end_to_end"]["ratio"]]
            met += sum(x >= TARGET_RATIO for x in ratios)
            rows += len(ratios)
        tables.append(f"`{path.relative_to(README.parent)}` "
                      f"(plot: `{path.with_suffix('.png').relative_to(README.parent)}`):\n\n"
                      + markdown_table(data["results"], data["meta"]))
    section = ("## Reference renderer throughput (`bench_reference.py`)\n\n"
               "`python -m bench.render.bench_reference --size small` renders each demo with the "
               "single-process reference renderer, records every ray it traces, and replays "
               "them through raw single-threaded Embree on the scene baked into world space. "
               "Per ray kind, *renderer* is the CPU time of `resolve_closest` (primary, "
               "secondary) or `unoccluded` (shadow); *raw* is one `EmbreeScene.run` call on "
               "the same rays; *ratio* = renderer rays/s / raw closest-hit rays/s. "
               "*End to end* divides all rays by the whole render's CPU time (generation "
               "and shading included). The last column splits the renderer's time into the "
               "top-level slab test, the Embree calls, and the rest (moving rays to local "
               "space, sorting and merging hits, quad lights).\n\n"
               + f"**Target (ratio >= {TARGET_RATIO}) met in {met} of {rows} rows.**\n\n"
               + "\n\n".join(tables))
    replace_section(README, README_BEGIN, README_END, section)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", choices=["tiny", "small", "default"], default="small")
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=None, help="default: 3/4 of the width")
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--bounces", type=int, default=5)
    ap.add_argument("--shadow-rays", type=int, default=4)
    ap.add_argument("--tile-size", type=int, default=RenderSettings().tile_size,
                    help="tile edge; with spp_per_pass = spp a pass holds tile^2 * spp paths")
    ap.add_argument("--scenes", default=",".join(DEMOS), help="comma-separated demo names")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--no-readme", action="store_true", help="do not update bench/README.md")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    height = args.height or max(1, args.width * 3 // 4)
    settings = RenderSettings(width=args.width, height=height, spp=args.spp,
                              bounces=args.bounces, shadow_rays=args.shadow_rays,
                              tile_size=args.tile_size, spp_per_pass=args.spp)
    results = {}
    for name in args.scenes.split(","):
        results[name] = bench_scene(name, args.size, settings)
        log.info("%s: %s", name, json.dumps(results[name]["end_to_end"]))
    meta = {"size": args.size, "width": args.width, "height": height, "spp": args.spp,
            "tile_size": args.tile_size,
            "bounces": args.bounces, "shadow_rays": args.shadow_rays,
            "machine": f"{platform.machine()}, {platform.python_implementation()} "
                       f"{platform.python_version()}, single thread",
            "settings": settings.model_dump()}
    table = markdown_table(results, meta)
    print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    stem = f"bench_reference_{args.size}_tile{args.tile_size}"
    (args.out / f"{stem}.json").write_text(json.dumps({"meta": meta, "results": results},
                                                      indent=2))
    plot(results, args.out / f"{stem}.png")
    if not args.no_readme and args.out.resolve() == RESULTS:
        write_readme_section(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
