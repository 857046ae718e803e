"""Numerical stability at the extremes: the block error of a demo moved by a similarity
(translation 1e0 to 1e7, uniform scale 1e-6 to 1e6, radiometry adjusted so the image must
not change) against the untouched demo, for the reference renderer, exact K = 4 and proxy
K = 4, next to each mode's two-seed noise level; and what the float64 ray origins cost on
the wire (bytes per ray) and in speed (rays per second).

    python -m bench.render.bench_extremes                                  # all of it
    python -m bench.render.bench_extremes --throughput-only --label before # speed and bytes only
    python -m bench.render.bench_extremes --label before --modes reference --no-throughput
    python -m bench.render.bench_extremes --report-only                    # tables from the JSON

Block error: the mean |difference| of 8x8-pixel block means over the mean block value
(`nprt.workers.stats.blocks`); averaging a block removes most sampling noise while a bias (a lost
shadow, a light leak) stays. Every transformed render uses the untouched render's seed, so
where nothing drifts the two images are nearly identical; the noise level is the block
error between two seeds of the untouched scene, and max |z| is the largest per-block
z-score with standard errors from those two seeds (the test suite fails at 4).

Rays per second (128x96, 4 spp, 3 bounces): the reference renderer's rays (all kinds) over
its CPU seconds (single thread, best of 6), and exact K = 4's rays over its wall time
(best of 2; K shards share 2 cores with other jobs, so read it as a cost, not a
speed-up). Bytes per ray: the row size of RayBatch / ShadowRayBatch and the measured
bytes over rays sent between shards.
The `before` records (`--label before`) were made on the commit before the float64
origins and the error-bound offsets, and show as a column of the tables.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: make the repository importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bench.common import RESULTS, add_output_flags, machine, publish, smoke, start_ray, timed_render  # noqa: E402,E501
from nprt.scene.demos import make_demo  # noqa: E402
from nprt.scene.transform import similarity, transform_scene  # noqa: E402
from nprt.workers.render import render  # noqa: E402
from nprt.workers.settings import RenderSettings  # noqa: E402
from nprt.workers.stats.blocks import block_error, block_z  # noqa: E402
from nprt.workers.wavefront.batch import RayBatch, ShadowRayBatch  # noqa: E402
from nprt.workers.wavefront.reference import ReferenceRenderer  # noqa: E402

log = logging.getLogger(__name__)

DEMOS = ("forest", "city")
MODES = ("reference", "exact", "proxy")
K = 4
# "Any direction": no axis-aligned shortcut for the translation.
DIRECTION = np.array([0.6, -0.48, 0.64]) / np.linalg.norm([0.6, -0.48, 0.64])
TRANSLATIONS = tuple(10.0 ** np.arange(0, 8))
SCALES = tuple(10.0 ** np.array([-6, -4, -2, 2, 4, 6]))
SEEDS = (1, 2)
THROUGHPUT_REPEATS = 6  # best of: the machine is shared, the minimum is the least disturbed


def settings(args, mode: str, seed: int) -> RenderSettings:
    return RenderSettings(width=args.width, height=args.height, spp=args.spp,
                          spp_per_pass=args.spp, bounces=args.bounces,
                          shadow_rays=args.shadow_rays, seed=seed,
                          shards=0 if mode == "reference" else K,
                          mode="exact" if mode == "reference" else mode)


def image(scene, s: RenderSettings) -> np.ndarray:
    """(h, w, 3) float32 image of one render (a fresh Coordinator per scene when K > 0)."""
    if s.shards == 0:
        return render(scene, s).film.image()
    return timed_render(scene, s)[1]


def transforms(args) -> list[tuple[str, float, np.ndarray]]:
    """(kind, value, (4, 4) similarity) for every point of the sweep."""
    out = [("translate", t, similarity(translate=t * DIRECTION)) for t in args.translations]
    return out + [("scale", s, similarity(scale=s)) for s in args.scales]


def sweep(args) -> dict:
    res = {}
    for name in args.demos:
        base = make_demo(name, args.size)
        res[name] = {}
        for mode in args.modes:
            t0 = time.perf_counter()
            ref, ref2 = (image(base, settings(args, mode, seed)) for seed in SEEDS)
            row = {"noise": block_error(ref2, ref),
                   "noise_max_z": float(np.abs(block_z(ref2, ref, ref2)).max()), "points": []}
            for kind, value, m in transforms(args):
                img = image(transform_scene(base, m), settings(args, mode, SEEDS[0]))
                z = np.abs(block_z(img, ref, ref2))
                row["points"].append({"kind": kind, "value": value,
                                      "block_error": block_error(img, ref),
                                      "max_z": float(z.max()),
                                      "finite": bool(np.isfinite(img).all())})
                log.info("%s %s %s %g: block error %.3g%%, max |z| %.2f", name, mode, kind,
                         value, 100 * row["points"][-1]["block_error"], z.max())
            row["seconds"] = round(time.perf_counter() - t0, 1)
            res[name][mode] = row
    return res


def throughput(args) -> dict:
    """Bytes per ray and rays per second on each demo, untouched."""
    out = {"ray_row_bytes": _row_bytes(RayBatch), "shadow_row_bytes": _row_bytes(ShadowRayBatch),
           "scenes": {}}
    for name in args.demos:
        scene = make_demo(name, args.size)
        s = RenderSettings(width=128, height=96, spp=4, spp_per_pass=4, bounces=3,
                           shadow_rays=2, seed=SEEDS[0])
        renderer = ReferenceRenderer(scene, s)
        best = np.inf
        for _ in range(THROUGHPUT_REPEATS + 1):  # the first warms Embree's BVHs and numba
            t0 = time.thread_time()
            result = render(scene, s, renderer=renderer)
            best = min(best, time.thread_time() - t0)
        rays = sum(result.stats.to_dict()["rays"].values())
        row, _, _ = timed_render(scene, s.model_copy(update={"shards": K}), repeat=2)
        dist_rays = sum(row["rays"].values())
        out["scenes"][name] = {
            "reference_rays": rays, "reference_cpu_s": round(best, 4),
            "reference_rays_per_s": round(rays / best),
            "exact_rays": dist_rays, "exact_render_s": row["render_s"],
            "exact_rays_per_s": round(dist_rays / row["render_s"]),
            "exact_transfers": row["total_transfers"], "exact_bytes": row["total_bytes"],
            "exact_bytes_per_transfer": round(row["total_bytes"] / max(row["total_transfers"], 1),
                                              2)}
    return out


def _row_bytes(batch_type) -> int:
    return int(sum(np.dtype(dt).itemsize * (w or 1) for w, dt in batch_type._SPEC.values()))


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    demos = list(res["sweep"])
    fig, axes = plt.subplots(len(demos), 2, figsize=(10, 3.6 * len(demos)), squeeze=False)
    colours = dict(zip((*MODES, "before"), ("tab:blue", "tab:orange", "tab:green", "tab:red"),
                       strict=True))
    for r, name in enumerate(demos):
        for c, kind in enumerate(("translate", "scale")):
            ax = axes[r, c]
            rows = dict(res["sweep"][name])
            if name in (res.get("sweep_before") or {}):
                rows["before"] = res["sweep_before"][name]["reference"]
            for mode, row in rows.items():
                pts = [p for p in row["points"] if p["kind"] == kind]
                label = {"reference": "reference", "before": "reference, before"}.get(
                    mode, f"{mode} K={K}")
                style, width = {"reference": ("o-", 4), "exact": ("s-", 2.5),
                                "proxy": ("^-", 1), "before": ("x:", 1.5)}[mode]
                ax.plot([p["value"] for p in pts], [100 * p["block_error"] for p in pts],
                        style, lw=width, ms=3 + width, color=colours[mode], label=label)
                if mode != "before":
                    ax.axhline(100 * row["noise"], color=colours[mode], ls="--", lw=1)
            ax.set_xscale("log")
            ax.set_xlabel("translation (scene units)" if kind == "translate" else "uniform scale")
            ax.set_ylabel("block error, %")
            ax.set_title(f"{name}:{res['size']} moved by {kind} (dashed: two-seed noise)")
            ax.set_yscale("symlog", linthresh=1e-3)
            ax.set_ylim(bottom=0)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def markdown(res: dict) -> str:
    a = res["args"]
    load = res["machine"]["load_average_before"][0]
    lines = [f"Size `{res['size']}`, {a['width']}x{a['height']}, {a['spp']} spp, "
             f"{a['bounces']} bounces, {a['shadow_rays']} shadow rays; translation along "
             f"{np.round(DIRECTION, 2).tolist()}; load average {load:.1f} "
             "before the run. Each cell: block error % (max |z|); the noise row compares two "
             "seeds of the untouched scene. \"reference, before\": the same sweep on the "
             "commit before float64 origins and error-bound offsets.", ""]
    before = res.get("sweep_before") or {}
    for name, modes in res["sweep"].items():
        names = ["reference" if m == "reference" else f"{m} K={K}" for m in modes]
        if name in before:
            modes = {"before": before[name]["reference"], **modes}
            names = ["reference, before"] + names
        lines += [f"**{name}**", "", "| transform | " + " | ".join(names) + " |",
                  "| --- |" + " ---: |" * len(modes)]
        lines.append("| noise (two seeds) | " + " | ".join(
            f"{100 * r['noise']:.2g} ({r['noise_max_z']:.2g})" for r in modes.values()) + " |")
        first = next(iter(modes.values()))["points"]
        for i, p in enumerate(first):
            cells = []
            for r in modes.values():
                q = r["points"][i]
                mark = "" if q["finite"] else " non-finite"
                cells.append(f"{100 * q['block_error']:.2g} ({q['max_z']:.2g}){mark}")
            lines.append(f"| {p['kind']} {p['value']:g} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def throughput_markdown(before: dict | None, after: dict) -> str:
    lines = ["| | before | after |", "| --- | ---: | ---: |"]
    b = before or {"scenes": {}}
    lines.append(f"| RayBatch row, bytes | {b.get('ray_row_bytes', '')} | "
                 f"{after['ray_row_bytes']} |")
    lines.append(f"| ShadowRayBatch row, bytes | {b.get('shadow_row_bytes', '')} | "
                 f"{after['shadow_row_bytes']} |")
    def cell(row: dict, key: str) -> str:
        if key not in row:
            return ""
        rounds = row.get(f"{key}_rounds")
        return f"{row[key]:,}" + (f" ({' / '.join(f'{r:,}' for r in rounds)})" if rounds else "")

    for name, row in after["scenes"].items():
        old = b["scenes"].get(name, {})
        for key, label in (("exact_bytes_per_transfer", "bytes per transferred ray, exact K=4"),
                           ("reference_rays_per_s", "rays/s, reference (CPU; best, rounds)"),
                           ("exact_rays_per_s", "rays/s, exact K=4 (wall; best, rounds)")):
            lines.append(f"| {name}: {label} | {cell(old, key)} | {cell(row, key)} |")
    return "\n".join(lines)


def summary(res: dict) -> str:
    """One sentence: the worst point after the change against the smallest noise level."""
    pts = [(p["block_error"], p["max_z"], name, mode, p)
           for name, modes in res["sweep"].items() for mode, row in modes.items()
           for p in row["points"]]
    worst_err, _, name, mode, p = max(pts, key=lambda x: x[0])
    worst_z = max(x[1] for x in pts)
    noise = min(row["noise"] for modes in res["sweep"].values() for row in modes.values())
    met = all(x[0] < noise for x in pts) and worst_z <= 4.0
    return (f"Target {'met' if met else 'NOT met'}: the largest block error is "
            f"{100 * worst_err:.2g} % ({name}, {mode}, {p['kind']} {p['value']:g}), "
            f"against a noise level of at least {100 * noise:.2g} %; the largest |z| is "
            f"{worst_z:.2g}.")


def _loads(record: dict | None) -> str:
    """The 1-minute load averages a throughput record was measured at."""
    if not record:
        return "?"
    machines = record.get("machine_rounds") or [record.get("machine", {})]
    return " / ".join(f"{m['load_average_before'][0]:.0f}" for m in machines if m)


def write_readme(res: dict, table: str, out: Path) -> None:
    before, after = res.get("throughput_before"), res["throughput"]
    section = "\n".join([
        "## Numerical stability at the extremes (`bench_extremes.py`)", "",
        "`python -m bench.render.bench_extremes` moves each demo by a similarity (translation "
        "1e0 to 1e7 along a skew direction, uniform scale 1e-6 to 1e6; radiometry adjusted "
        "by `nprt.scene.transform` so the image must not change) and compares it with the "
        "untouched demo, rendered with the same seed, by 8x8 block means. See the module "
        "docstring for the definitions. Target: every point at the noise level (dashed in "
        "the plot).", "",
        "`results/bench_extremes.json` (plot: `results/bench_extremes.png`):", "",
        "![](results/bench_extremes.png)", "", summary(res), "", table, "",
        "Cost of float64 ray origins. Before: the commit before them "
        "(`--throughput-only --label before`); after: `--throughput-only`. Rounds were run "
        f"alternately on the shared 2-core machine at load averages {_loads(before)} "
        f"(before) and {_loads(after)} (after); ray and transfer counts are the same on "
        "both sides, so rays/s differences within the spread of the rounds are noise:", "",
        throughput_markdown(before, after)])
    publish("bench_extremes", section, out)


def report(res: dict, out: Path, readme: bool) -> None:
    """Plot and tables from a finished run, with the throughput records and the before
    sweep in `out` where they exist (the latest throughput record wins)."""
    for file, key in (("bench_extremes_throughput_before.json", "throughput_before"),
                      ("bench_extremes_throughput_after.json", "throughput"),
                      ("bench_extremes_before.json", "sweep_before")):
        path = out / file
        if path.exists():
            res[key] = json.loads(path.read_text())
        else:
            res.setdefault(key, None)
    if res["sweep_before"] is not None:
        res["sweep_before"] = res["sweep_before"]["sweep"]
    plot(res, out / "bench_extremes.png")
    table = markdown(res)
    print(table)
    if res["throughput"] is not None:
        print(throughput_markdown(res["throughput_before"], res["throughput"]))
    if readme:
        write_readme(res, table, out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--demos", nargs="+", default=list(DEMOS))
    ap.add_argument("--size", default="small")
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--height", type=int, default=48)
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--bounces", type=int, default=3)
    ap.add_argument("--shadow-rays", type=int, default=2)
    ap.add_argument("--translations", type=float, nargs="+", default=list(TRANSLATIONS))
    ap.add_argument("--scales", type=float, nargs="+", default=list(SCALES))
    ap.add_argument("--ray-cpus", type=int, default=K)
    ap.add_argument("--throughput-only", action="store_true")
    ap.add_argument("--no-throughput", action="store_true")
    ap.add_argument("--label", default="after",
                    help="'before': a record of the code before float64 origins (no README)")
    ap.add_argument("--report-only", action="store_true",
                    help="redo plot, tables and README from the saved results")
    add_output_flags(ap, RESULTS)
    # smoke: the reference only (exact K = 4 starts a pool per image: seconds each)
    args = smoke(ap.parse_args(argv), demos=["forest"], size="tiny", modes=["reference"],
                 width=16, height=12, spp=1, bounces=1, shadow_rays=1, translations=[1e3],
                 scales=[1e-3], no_throughput=True)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    result_path = args.out / ("bench_extremes.json" if args.label == "after"
                              else f"bench_extremes_{args.label}.json")
    if args.report_only:
        report(json.loads(result_path.read_text()), args.out, not args.no_readme)
        return 0
    if set(args.modes) != {"reference"} or not args.no_throughput:  # the reference needs no Ray
        start_ray(args.ray_cpus)
    args.out.mkdir(parents=True, exist_ok=True)
    res = {"size": args.size, "machine": machine(args.ray_cpus),
           "args": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}}
    if not args.no_throughput:
        res["throughput"] = throughput(args)
        tp_path = args.out / f"bench_extremes_throughput_{args.label}.json"
        tp_path.write_text(json.dumps({**res["throughput"], "machine": res["machine"]},
                                      indent=1))
        if args.throughput_only:
            print(throughput_markdown(None, res["throughput"]))
            return 0
    res["sweep"] = sweep(args)
    result_path.write_text(json.dumps(res, indent=1))
    if args.label == "after":
        report(res, args.out, not args.no_readme)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
