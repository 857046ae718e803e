"""Helpers shared by the render benchmarks: one timed distributed render, the machine
record, and replacing a marked section of bench/README.md (or the top-level README)."""

from __future__ import annotations

import json
import os
import platform
import re
import time
from pathlib import Path

import numpy as np
import ray

from nprt.scene.model import Scene
from nprt.workers.render import render
from nprt.workers.runtime.coordinator import Coordinator
from nprt.workers.settings import RenderSettings
from nprt.workers.stats.quality import compare

BENCH_README = Path(__file__).resolve().parent / "README.md"


def machine(ray_cpus: int) -> dict:
    return {"platform": platform.platform(), "python": platform.python_version(),
            "cpus": os.cpu_count(), "ray": ray.__version__, "ray_cpus": ray_cpus,
            "load_average_before": os.getloadavg()}


def timed_render(scene: Scene, s: RenderSettings, on_pass=None, repeat: int = 1):
    """Start a Coordinator (timed as prepare: plan, proxies, actors), render `repeat`
    times and keep the fastest. Returns (row, image (h, w, 3) float32, coordinator info)."""
    t0 = time.perf_counter()
    coord = Coordinator(scene, s)
    prepare_s = time.perf_counter() - t0
    try:
        best = None
        for _ in range(repeat):
            t0 = time.perf_counter()
            result = render(scene, s, renderer=coord, on_pass=on_pass)
            wall = time.perf_counter() - t0
            if best is None or wall < best[0]:
                best = (wall, result)
        info = coord.info()
    finally:
        coord.close()
    wall, result = best
    st = result.stats.to_dict()
    row = {"mode": s.mode, "k": s.shards, "prepare_s": round(prepare_s, 3),
           "render_s": round(wall, 3), "transfers": st["transfers"], "bytes": st["bytes"],
           "total_transfers": st["total_transfers"], "total_bytes": st["total_bytes"],
           "rays": st["rays"], "hops_histogram": st["hops_histogram"],
           "phase_s": st["phase_s"], "counters": st["counters"]}
    return row, result.film.image(), info


def bench_scene(name: str, size: str) -> Scene:
    """A demo scene, or the test family's overlapping-instances scene ("family")."""
    if name == "family":
        from nprt.scene.demos import family

        return family.build(size)
    from nprt.scene.demos import make_demo

    return make_demo(name, size)


def quality(base: np.ndarray, img: np.ndarray) -> dict:
    """PSNR (dB, inf when identical), SSIM and mean FLIP of img against base."""
    return {k: round(v, 5) for k, v in compare(base, img).items()}


def replace_section(readme: Path, begin: str, end: str, section: str) -> None:
    """Replace the text between the markers (inclusive) with section, or append it."""
    text = readme.read_text() if readme.exists() else "# Benchmarks\n"
    pattern = re.compile(re.escape(begin) + ".*?" + re.escape(end), re.S)
    block = f"{begin}\n{section}\n{end}"
    text = pattern.sub(lambda _: block, text) if pattern.search(text) \
        else text.rstrip("\n") + "\n\n" + block + "\n"
    readme.write_text(text)


def add_render_flags(ap, results: Path) -> None:
    """Image, sampling and output flags every render benchmark takes."""
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=None, help="default: 3/4 of the width")
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--bounces", type=int, default=5)
    ap.add_argument("--shadow-rays", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=results)
    ap.add_argument("--no-readme", action="store_true", help="do not update the README")


def render_settings(args, **kw) -> RenderSettings:
    return RenderSettings(width=args.width, height=args.height or args.width * 3 // 4,
                          spp=args.spp, spp_per_pass=args.spp, bounces=args.bounces,
                          shadow_rays=args.shadow_rays, seed=args.seed, **kw)


def save(res: dict, path: Path, plot, markdown) -> str:
    """Write res as JSON and its plot (same stem, .png); print and return the table."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(res, indent=1))
    plot(res, path.with_suffix(".png"))
    table = markdown(res)
    print(table)
    print(f"\nwrote {path} and {path.with_suffix('.png')}")
    return table
