"""The accuracy target kept, and what it buys: per scene, exact, the oracle's transfer bound
and proxy mode at several targets (`ProxySettings.accuracy`), each with the predicted PSNR,
the exact check of scattered 8x8 blocks (measured PSNR and its 95 % interval) and the PSNR of
the whole image against exact at the same seed and K; ray bytes and render wall beside them.

    python -m bench.proxy.bench_proxy_accuracy [--scenes foliage:default forest:default ...]
        [--targets 30 35 40 45] [--shards 4] [--width 160] [--spp 4]

Writes results/proxy_accuracy.json and .png (target dB against render wall and ray bytes).
The foliage scene (scene/demos/family.build_foliage) tuned nothing: the constants of
nprt.proxies.accuracy were fitted on the demos (`--fit` prints the fit from this run's rows).
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

import numpy as np

from bench.common import (
    RESULTS,
    add_render_flags,
    finish,
    quality,
    render_settings,
    smoke,
    start_ray,
)
from nprt.proxies.ship import TEST_STEPS

SECTION = "bench_proxy_accuracy"


def scene_of(spec: str):
    from bench.common import bench_scene
    from nprt.scene.demos import family

    name, size = spec.split(":")
    return family.build_foliage(size) if name == "foliage" else bench_scene(name, size)


def _render(scene, s, proxy_dir, repeat: int = 1):
    """(row, film, report or None): the fastest of `repeat` renders on a pool of its own,
    then (proxy mode) the exact check on another, once the first is closed."""
    from nprt.proxies.check import run_check
    from nprt.workers.render import render
    from nprt.workers.runtime.coordinator import Coordinator

    t0 = time.perf_counter()
    coord = Coordinator(scene, s, proxy_dir=proxy_dir)
    prepare_s = time.perf_counter() - t0
    try:
        wall = cpu = math.inf
        for _ in range(repeat):  # the same image every time: keep the fastest
            t0 = time.perf_counter()
            result = render(scene, s, renderer=coord)
            wall = min(wall, time.perf_counter() - t0)
            cpu = min(cpu, result.info["cpu_s"])  # this render's, coordinator and shards
    finally:
        coord.close()
    st = result.stats.to_dict()
    row = {"mode": s.mode, "accuracy": s.proxy.accuracy if s.mode == "proxy" else None,
           "prepare_s": round(prepare_s, 3), "render_s": round(wall, 3),
           "cpu_s": round(cpu, 3),
           "total_bytes": st["total_bytes"], "bytes": st["bytes"],
           "transfers": st["transfers"], "rays": st["rays"],
           "proxy_counters": {k: v for k, v in st["counters"].items() if k.startswith("proxy")}}
    report = None
    if s.mode == "proxy":
        report = run_check(scene, s, result.film, result.info["accuracy"], proxy_dir=proxy_dir)
        row["plan"] = [{k: d[k] for k in ("name", "decision", "width", "accuracy")}
                       for d in result.info["proxy_plan"]["decisions"]]
    return row, result.film, report


def run_scene(spec: str, args) -> list[dict]:
    from nprt.workers.settings import ProxySettings

    scene = scene_of(spec)
    base = render_settings(args, shards=args.shards)
    knobs = dict(width=args.proxy_width, steps=args.proxy_steps)
    exact_row, exact_film, _ = _render(scene, base, args.proxy_dir, args.repeat)
    oracle = base.model_copy(update={"mode": "oracle",
                                     "proxy": ProxySettings(**knobs)})
    oracle_row, _, _ = _render(scene, oracle, args.proxy_dir)
    rows = [exact_row, oracle_row]
    for target in args.targets:
        s = base.model_copy(update={"mode": "proxy", "proxy": ProxySettings(
            accuracy=target, **knobs)})
        row, film, report = _render(scene, s, args.proxy_dir, args.repeat)
        row["quality_vs_exact"] = quality(exact_film.image(), film.image())
        row["report"] = report
        rows.append(row)
        print(f"{spec} target {target}: whole image {row['quality_vs_exact']['psnr_db']:.2f} "
              f"dB, check {report['check']['psnr_db']} {report['check']['interval_db']}, "
              f"predicted {report['predicted_db']}, {row['total_bytes'] / 1e6:.2f} MB, "
              f"{row['render_s']:.2f} s", flush=True)
    for r in rows:
        r["scene"] = spec
        r["bytes_vs_exact"] = round(exact_row["total_bytes"] / max(1, r["total_bytes"]), 3)
    return rows


def _db(x) -> str:
    return "inf" if x is None or (isinstance(x, float) and math.isinf(x)) else f"{x:.2f}"


def markdown(res: dict) -> str:
    lines = ["| scene | mode | target | predicted dB | check dB (95 % interval) | whole image dB "
             "| within 2 dB | met | MB | bytes vs exact | render s | CPU s | check s |",
             "| --- | --- | ---: | ---: | --- | ---: | --- | --- |" + " ---: |" * 5]
    for r in res["rows"]:
        rep = r.get("report")
        if rep is None:
            lines.append(f"| {r['scene']} | {r['mode']} | | | | | | | "
                         f"{r['total_bytes'] / 1e6:.2f} | {r['bytes_vs_exact']:.2f}x | "
                         f"{r['render_s']:.2f} | {r['cpu_s']:.2f} | |")
            continue
        c, whole = rep["check"], r["quality_vs_exact"]["psnr_db"]
        lo, hi = c["interval_db"]
        close = c["psnr_db"] is None and math.isinf(whole) or (
            c["psnr_db"] is not None and abs(c["psnr_db"] - min(whole, 99.0)) <= 2.0)
        lines.append(
            f"| {r['scene']} | proxy | {r['accuracy']} | {_db(rep['predicted_db'])} | "
            f"{_db(c['psnr_db'])} ({_db(lo)} to {_db(hi)}) | {_db(whole)} | "
            f"{'yes' if close else '**no**'} | {'yes' if rep['met'] else '**MISSED**'} | "
            f"{r['total_bytes'] / 1e6:.2f} | {r['bytes_vs_exact']:.2f}x | {r['render_s']:.2f} | "
            f"{r['cpu_s']:.2f} | {c['wall_s']:.1f} |")
    return "\n".join(lines)


def plot(res: dict, png: Path) -> None:
    import matplotlib.pyplot as plt

    fig, (a, c, b) = plt.subplots(1, 3, figsize=(14, 3.8))
    for spec in dict.fromkeys(r["scene"] for r in res["rows"]):
        rows = [r for r in res["rows"] if r["scene"] == spec and r["mode"] == "proxy"]
        t = [r["accuracy"] for r in rows]
        a.plot(t, [r["render_s"] for r in rows], "o-", label=spec)
        if all("cpu_s" in r for r in rows):
            c.plot(t, [r["cpu_s"] for r in rows], "o-", label=spec)
        b.plot(t, [r["total_bytes"] / 1e6 for r in rows], "o-", label=spec)
    a.set(xlabel="accuracy target, dB", ylabel="render wall, s", title="render time")
    c.set(xlabel="accuracy target, dB", ylabel="CPU s (coordinator + shards)", title="CPU")
    b.set(xlabel="accuracy target, dB", ylabel="ray bytes, MB", title="ray bytes")
    b.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def fit(rows: list[dict]) -> dict:
    """Least squares, non-negative: whole-image MSE = a^2 r_sec^2 + b^2 r_shadow^2 over the
    demo rows (r: wrong answers per ray, from the measured query shares)."""
    from scipy.optimize import nnls

    x, y = [], []
    for r in rows:
        if r.get("report") is None or r["scene"].startswith("foliage"):
            continue
        w = r["report"]["prediction"]["measured_shares"]["wrong_per_ray"]
        x.append([w["secondary"] ** 2, w["shadow"] ** 2])
        y.append(10 ** (-min(r["quality_vs_exact"]["psnr_db"], 99.0) / 10))
    coef, _ = nnls(np.array(x), np.array(y))
    return {"secondary": float(np.sqrt(coef[0])), "shadow": float(np.sqrt(coef[1]))}


def main(argv=None) -> int:
    import ray

    ap = argparse.ArgumentParser(prog="python -m bench.proxy.bench_proxy_accuracy",
                                 description=__doc__)
    ap.add_argument("--scenes", nargs="+", default=["foliage:default", "forest:default",
                                                     "sculpture:default", "city:default"])
    ap.add_argument("--targets", nargs="+", type=float, default=[30.0, 35.0, 40.0, 45.0])
    ap.add_argument("--shards", type=int, default=4)
    ap.add_argument("--proxy-width", type=int, default=None)
    ap.add_argument("--proxy-steps", type=int, default=12000)
    ap.add_argument("--proxy-dir", default=None, help="user proxy cache (default: nprt's)")
    ap.add_argument("--fit", action="store_true", help="print the sensitivity fit")
    ap.add_argument("--repeat", type=int, default=3, help="renders per row, the fastest kept")
    ap.add_argument("--tag", default="", help="results/proxy_accuracy_<tag>.json (and .png);"
                    " the README table is left alone")
    add_render_flags(ap, RESULTS)
    # The smoke renders with the foliage:tiny proxies shipped at width 16 (proxies/ship.py,
    # TEST_STEPS): the planner finds them in the cache and trains nothing.
    args = smoke(ap.parse_args(argv), scenes=["foliage:tiny"], targets=[30.0],
                 shards=2, width=32, height=24, spp=1, bounces=2, proxy_width=16,
                 proxy_steps=TEST_STEPS, repeat=1)
    start_ray(max(args.shards, 2))
    try:
        rows = [r for spec in args.scenes for r in run_scene(spec, args)]
    finally:
        ray.shutdown()
    res = {"args": {k: str(v) for k, v in vars(args).items()}, "load": os.getloadavg(),
           "rows": rows}
    if args.fit:
        res["fit"] = fit(rows)
        print("sensitivity fit:", res["fit"])
    intro = ("`python -m bench.proxy.bench_proxy_accuracy` (`{json}`, plot `{png}`). K = "
             f"{args.shards}, {args.width}x{args.height or args.width * 3 // 4}, {args.spp} "
             f"spp, seed 0, default settings but the target; render s: the fastest of "
             f"{args.repeat} renders on one pool (load {os.getloadavg()[0]:.1f} at the end). "
             "*check*: scattered 8x8 blocks rendered exactly afterwards (check s: its wall, "
             "a pool start included); *met*: the check's upper bound reaches the target; "
             "*within 2 dB*: check against the whole image's PSNR.\n\n"
             "![]({png})\n\n")
    name = "proxy_accuracy" + (f"_{args.tag}" if args.tag else "")
    # A tagged run (one scene, a side-by-side) keeps its own files; the README table is the
    # untagged run's.
    finish(res, args.out / f"{name}.json", plot=plot, markdown=markdown,
           section=SECTION, intro=intro, update_readme=not (args.no_readme or args.tag))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
