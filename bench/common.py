"""Helpers shared by the benchmarks: where results go (`RESULTS`), the epilogue every script
ends with (`finish`: JSON, plot, table, and its marked section of bench/README.md or the
top-level README), the `--smoke` flag of the CI smoke test (tests/test_bench_smoke.py), the
driver's Ray (`start_ray`), one timed distributed render and the machine record.

`NPRT_BENCH_RESULTS` moves `RESULTS` elsewhere (the smoke test points it at a temporary
folder); a README section is only written for results that lie beside that README."""

from __future__ import annotations

import json
import os
import platform
import re
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # imported where used: bench_massive's bare driver imports this module
    import numpy as np

    from nprt.scene.model import Scene
    from nprt.workers.settings import RenderSettings

BENCH_README = Path(__file__).resolve().parent / "README.md"
ROOT_README = BENCH_README.parents[1] / "README.md"
RECORDED = BENCH_README.parent / "results"  # the results bench/README.md shows
RESULTS = Path(os.environ.get("NPRT_BENCH_RESULTS") or RECORDED)


def machine(ray_cpus: int) -> dict:
    import ray

    return {"platform": platform.platform(), "python": platform.python_version(),
            "cpus": os.cpu_count(), "ray": ray.__version__, "ray_cpus": ray_cpus,
            "load_average_before": os.getloadavg()}


_TICK = os.sysconf("SC_CLK_TCK")


def child_env(**extra: str) -> dict:
    """The environment of a benchmark's child Python process: this one's, with the
    repository root first on PYTHONPATH (so `-m bench...` and `-c` children import this
    checkout), and extra set."""
    root = str(BENCH_README.parents[1])
    path = os.pathsep.join(filter(None, (root, os.environ.get("PYTHONPATH"))))
    return {**os.environ, "PYTHONPATH": path, **extra}


def proc_cpu(pid: int) -> float:
    """User + system CPU seconds of every thread of process pid, so far."""
    return stat_cpu(f"/proc/{pid}/stat")


def stat_cpu(path: str) -> float:
    """User + system CPU seconds in a /proc stat file: /proc/<pid>/stat (the process) or
    /proc/<pid>/task/<tid>/stat (one thread)."""
    with open(path) as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / _TICK


def raylet_cpu_s() -> float | None:
    """CPU seconds so far of the raylet of the Ray this driver started (None: it joined
    one, or none is running). A parcel above the inline limit
    (nprt.workers.runtime.raysession) goes through the object store, whose put, seal, pin
    and free the raylet does: CPU in neither a shard's nor the coordinator's total."""
    import ray

    node = getattr(ray._private.worker, "_global_node", None) if ray.is_initialized() else None
    procs = node.all_processes.get("raylet") if node is not None else None
    if not procs:
        return None
    try:
        return proc_cpu(procs[0].process.pid)
    except OSError:  # it ended
        return None


def start_ray(num_cpus: int | None = None) -> None:
    """ray.init for a benchmark driver: a local Ray of num_cpus CPUs, or the running cluster
    RAY_ADDRESS names, with that cluster's CPUs (the smoke test shares one among its runs:
    starting a Ray takes seconds). Worker output and Ray's notices stay off the console."""
    import logging

    import ray

    from nprt.workers.runtime.raysession import RAY_SYSTEM_CONFIG

    shared = os.environ.get("RAY_ADDRESS", "") not in ("", "local")
    # "local" when no cluster is named: ray.init() with no address joins whatever Ray
    # /tmp/ray/ray_current_cluster points at (a test's cluster, another bench's). A Ray
    # started here takes the system config nprt's own start gives it (a joined one has
    # its head's).
    ray.init(address=None if shared else "local", num_cpus=None if shared else num_cpus,
             include_dashboard=False, _system_config=None if shared else dict(RAY_SYSTEM_CONFIG),
             log_to_driver=False, logging_level=logging.WARNING)


def timed_render(scene: Scene, s: RenderSettings, on_pass=None, repeat: int = 1,
                 trace: bool = False):
    """Start a renderer (a Coordinator, or the reference for shards=0; timed as prepare:
    plan, proxies, actors), render `repeat` times and keep the fastest. Returns (row,
    image (h, w, 3) float32, renderer info). trace: a Coordinator records its steps, and
    info gains "trace" (StepTrace.to_dict(), every repeat's steps: use repeat=1) and
    "window"."""
    from nprt.workers.render import make_renderer, render

    t0 = time.perf_counter()
    coord = make_renderer(scene, s, trace=trace and s.shards > 0)
    prepare_s = time.perf_counter() - t0
    try:
        best = None
        for _ in range(repeat):
            r0, t0 = raylet_cpu_s(), time.perf_counter()
            result = render(scene, s, renderer=coord, on_pass=on_pass)
            wall, r1 = time.perf_counter() - t0, raylet_cpu_s()
            if best is None or wall < best[0]:
                best = (wall, result, None if None in (r0, r1) else r1 - r0)
        info = coord.info()
        if getattr(coord, "trace", None) is not None:
            info |= {"trace": coord.trace.to_dict(), "window": coord.window}
    finally:
        coord.close()
    wall, result, raylet = best
    st = result.stats.to_dict()
    row = {"mode": s.mode if s.shards else "reference", "k": s.shards,
           "prepare_s": round(prepare_s, 3),
           "render_s": round(wall, 3),
           "raylet_cpu_s": None if raylet is None or not s.shards else round(raylet, 3),
           "transfers": st["transfers"], "bytes": st["bytes"],
           "total_transfers": st["total_transfers"], "total_bytes": st["total_bytes"],
           "rays": st["rays"], "hops_histogram": st["hops_histogram"],
           "phase_s": st["phase_s"], "phase_cpu_s": st["phase_cpu_s"],
           "counters": st["counters"]}
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
    from nprt.workers.stats.quality import compare

    return {k: round(v, 5) for k, v in compare(base, img).items()}


def replace_section(readme: Path, begin: str, end: str, section: str) -> None:
    """Replace the text between the markers (inclusive) with section, or append it."""
    text = readme.read_text() if readme.exists() else "# Benchmarks\n"
    pattern = re.compile(re.escape(begin) + ".*?" + re.escape(end), re.S)
    block = f"{begin}\n{section}\n{end}"
    text = pattern.sub(lambda _: block, text) if pattern.search(text) \
        else text.rstrip("\n") + "\n\n" + block + "\n"
    readme.write_text(text)


def publish(name: str, section: str, results: Path, readme: Path = BENCH_README) -> bool:
    """Replace readme's `<!-- name:begin -->` ... `<!-- name:end -->` section, only when
    `results` (a file or folder the section links to) lies beside the README: never for a
    --smoke run or results written elsewhere. Returns whether it wrote."""
    try:
        Path(results).resolve().relative_to(readme.parent.resolve())
    except ValueError:
        print(f"{readme.name} not updated: {results} is outside {readme.parent}")
        return False
    replace_section(readme, f"<!-- {name}:begin -->", f"<!-- {name}:end -->", section)
    return True


def finish(res: dict, path: Path, *, plot=None, markdown=None, section: str | None = None,
           intro: str = "", readme: Path = BENCH_README, update_readme: bool = True,
           table_file: bool = False) -> str:
    """The epilogue of a benchmark: write res as JSON at path, its plot (plot(res, png)) as
    the .png beside it, print the table (markdown(res); also the .md beside it with
    table_file) and, when `section` names a README section and update_readme, replace that
    section with intro + table (`publish`). In intro, `{json}` and `{png}` stand for the
    result files relative to the README. Returns the table."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(res, indent=1, default=str))
    png = path.with_suffix(".png")
    if plot is not None:
        plot(res, png)
    table = markdown(res) if markdown is not None else ""
    if table_file:
        path.with_suffix(".md").write_text(table + "\n")
    print(table)
    print(f"\nwrote {path}" + (f" and {png}" if plot is not None else ""))
    if section and update_readme:
        try:
            rel = path.resolve().relative_to(readme.parent.resolve())
        except ValueError:
            rel = path
        text = intro.replace("{json}", str(rel)).replace("{png}", str(rel.with_suffix(".png")))
        publish(section, text + table, path, readme)
    return table


def fmt_or_blank(x, spec: str, unit: str = "") -> str:
    """x formatted with spec (and unit) for a table cell; blank where x is None."""
    return "" if x is None else f"{x:{spec}}{unit}"


def window_arg(text: str) -> int:
    """argparse type of a coordinator window (passes live at once): 1 or more."""
    import argparse

    n = int(text) if text.isdigit() else 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"a window is a number of passes, 1 or more: {text!r}")
    return n


def add_render_flags(ap, results: Path) -> None:
    """Image, sampling and output flags every render benchmark takes."""
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=None, help="default: 3/4 of the width")
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--bounces", type=int, default=5)
    ap.add_argument("--shadow-rays", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    add_output_flags(ap, results)


def add_image_flags(ap, width: int = 640, height: int = 360, spp: int = 16) -> None:
    """--scenes (demo names; forest and city), --size and the image: the flags of the
    scaling benchmarks, which render the issue's image by default."""
    ap.add_argument("--scenes", nargs="+", default=["forest", "city"])
    ap.add_argument("--size", default="default")
    ap.add_argument("--width", type=int, default=width)
    ap.add_argument("--height", type=int, default=height)
    ap.add_argument("--spp", type=int, default=spp)


def add_byte_slack_flag(ap) -> None:
    """--byte-slack: the distributed runs' RenderSettings.byte_slack (the placement's cap on
    a shard's bytes, x the bytes-only rule's largest shard)."""
    from nprt.scene.partition import BYTE_SLACK

    ap.add_argument("--byte-slack", type=float, default=BYTE_SLACK,
                    help="RenderSettings.byte_slack of the distributed runs: the placement's "
                         "cap on a shard's bytes, x the bytes-only rule's largest shard "
                         f"(default {BYTE_SLACK:g})")


def stored_scene(name: str, size: str):
    """The demo scene `name` at `size` ("default": the demo's own) from the scene store,
    as add_image_flags' --scenes and --size name it (call .load() for its geometry)."""
    from nprt.scene.store import open_scene

    return open_scene(name if size == "default" else f"{name}:{size}")


def placeable_ks(ks, scene, name: str) -> list[int]:
    """The shard counts of ks that `scene` (Scene or SceneMeta) can be placed on: a shard
    owns one instance or more, so K above the instance count is skipped with a line that
    says so, instead of failing the run after its smaller K (the default K list follows
    the machine's cores, not the scene)."""
    n = len(scene.instances)
    kept = [k for k in ks if k <= n]
    if len(kept) < len(ks):
        print(f"{name}: {n} instances, so K = {', '.join(str(k) for k in ks if k > n)} "
              f"skipped (a shard owns one instance or more)", flush=True)
    return kept


def add_output_flags(ap, out: Path = RESULTS) -> None:
    """--out, --no-readme and --smoke (the smallest input; never writes a README)."""
    ap.add_argument("--out", type=Path, default=out)
    ap.add_argument("--no-readme", action="store_true", help="do not update the README")
    ap.add_argument("--smoke", action="store_true",
                    help="smallest input, for the CI smoke test (implies --no-readme)")


def smoke(args, **tiny):
    """With --smoke, replace args' values by the tiny ones given and set no_readme."""
    if getattr(args, "smoke", False):
        for k, v in tiny.items():
            setattr(args, k, v)
        args.no_readme = True
    return args


def render_settings(args, **kw) -> RenderSettings:
    from nprt.workers.settings import RenderSettings

    return RenderSettings(width=args.width, height=args.height or args.width * 3 // 4,
                          spp=args.spp, spp_per_pass=args.spp, bounces=args.bounces,
                          shadow_rays=args.shadow_rays, seed=args.seed, **kw)
