"""The speed/accuracy trade of the proxy mode: ray bytes and wall time against PSNR and
FLIP (vs exact, same seed), sweeping one knob at a time around the defaults: visibility
threshold, confidence band (secondary rays), shadow band, proxy width and training budget.

    python -m bench.proxy.bench_proxy_sweep --scene forest --size default

Widths and step budgets other than the shipped ones (narrowest of 16/32/64 meeting 97 %,
ProxyConfig.steps optimiser steps) are trained on first use into the user cache, so a first
run takes minutes longer; their training time is reported. The exact and oracle renders of
the same run are the anchors. Writes results/proxy_sweep_<scene>_<size>.{json,png} and the
plot and table into the top-level README.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
from pathlib import Path

import ray
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from bench.common import (
    RESULTS,
    ROOT_README,
    add_render_flags,
    finish,
    machine,
    quality,
    render_settings,
    smoke,
    start_ray,
    timed_render,
)
from nprt.proxies.config import ProxyConfig
from nprt.scene.demos import DEMOS, make_demo
from nprt.workers.settings import ProxySettings

# One knob at a time; every other knob at its default (ProxySettings()).
SWEEPS = {
    "threshold": [0.3, 0.4, None, 0.6, 0.7],  # None: each proxy's calibrated threshold
    "band": [0.0, 0.1, 0.2, 0.3, 0.4, 0.5],
    "shadow_band": [0.0, 0.05, 0.1, 0.2, 0.4],
    "width": [16, 32, 64],
    "steps": [4000, 12000, 24000],  # 12000: the default
}
PSNR_CAP = 80.0  # identical images (inf dB) are drawn here


def points(knobs=tuple(SWEEPS), per_knob: int | None = None
           ) -> list[tuple[str, object, ProxySettings]]:
    """(knob, value, settings) for the first per_knob values (all: None) of each knob; the
    default settings appear once per knob that has it."""
    out = []
    for knob in knobs:
        for v in SWEEPS[knob][:per_knob]:
            kw = {knob: v}
            if knob == "steps":
                kw["width"] = 16  # one width, so the step budget alone changes
            out.append((knob, v, ProxySettings(**kw)))
    return out


def run(args) -> dict:
    base = render_settings(args, shards=args.shards)
    start_ray(args.shards)
    scene = make_demo(args.scene, args.size)
    todo = points(args.knobs, args.per_knob)
    out = {"scene": args.scene, "size": args.size, "settings": base.model_dump(),
           "machine": machine(args.shards), "anchors": {}, "points": []}
    columns = (TextColumn("{task.description:<30}"), BarColumn(), MofNCompleteColumn(),
               TimeElapsedColumn())
    try:
        with Progress(*columns) as bar:
            task = bar.add_task("renders", total=2 + len(todo))
            anchors = {}
            for mode in ("exact", "oracle"):
                bar.update(task, description=mode)
                row, img, _ = timed_render(scene, base.model_copy(update={"mode": mode}))
                anchors[mode] = (row, img)
                bar.advance(task)
            exact_img = anchors["exact"][1]
            for mode, (row, img) in anchors.items():
                out["anchors"][mode] = {**row, "quality_vs_exact": quality(exact_img, img)}
            for knob, value, knobs in todo:
                bar.update(task, description=f"{knob}={value}")
                s = base.model_copy(update={"mode": "proxy", "proxy": knobs})
                row, img, info = timed_render(scene, s)
                plan = info["proxy_plan"]
                row.update(knob=knob, value=value, proxy=knobs.model_dump(),
                           quality_vs_exact=quality(exact_img, img),
                           proxy_bytes=plan["proxy_bytes"],
                           train_s=sum(d["train_s"] or 0.0 for d in plan["decisions"]
                                       if d["decision"] == "proxy"),
                           widths=sorted({d["width"] for d in plan["decisions"]
                                          if d["decision"] == "proxy"}))
                out["points"].append(row)
                bar.advance(task)
        out["machine"]["load_average_after"] = os.getloadavg()
    finally:
        ray.shutdown()
    return out


def _psnr(q: dict) -> float:
    return PSNR_CAP if math.isinf(q["psnr_db"]) else q["psnr_db"]


def markdown(res: dict) -> str:
    s = res["settings"]
    ex = res["anchors"]["exact"]
    lines = [f"`{res['scene']}` size `{res['size']}`, K={s['shards']}, {s['width']}x"
             f"{s['height']}, {s['spp']} spp, {s['bounces']} bounces, seed {s['seed']}; "
             f"{res['machine']['cpus']} cores. One knob at a time, the others at their "
             f"defaults (threshold: each proxy's calibrated one; band {ProxySettings().band}; "
             f"shadow band {ProxySettings().shadow_band}; "
             f"width: narrowest of 16/32/64 reaching 97 %; budget {ProxyConfig.steps} steps). "
             "Bytes are ray batches sent between shards; quality is against exact at the same "
             "seed.", "",
             "| knob | value | ray MB | bytes vs exact | secondary / shadow transfers | "
             "render s | PSNR dB | SSIM | FLIP | mispredicted / uncertain | proxy widths | "
             "proxies kB | training s |",
             "| --- | --- | ---: | ---: | --- | ---: | ---: | ---: | ---: | --- | --- | ---: "
             "| ---: |"]
    for mode, r in res["anchors"].items():
        q = r["quality_vs_exact"]
        lines.append(f"| *{mode}* | | {r['total_bytes'] / 1e6:.2f} | "
                     f"{ex['total_bytes'] / max(r['total_bytes'], 1):.2f}x | "
                     f"{r['transfers']['secondary']:,} / {r['transfers']['shadow']:,} | "
                     f"{r['render_s']:.2f} | {q['psnr_db']:.2f} | {q['ssim']:.4f} | "
                     f"{q['flip']:.4f} | | | | |")
    for r in res["points"]:
        q, c = r["quality_vs_exact"], r["counters"]
        value = "calibrated" if r["value"] is None else r["value"]
        lines.append(f"| {r['knob']} | {value} | {r['total_bytes'] / 1e6:.2f} | "
                     f"{ex['total_bytes'] / max(r['total_bytes'], 1):.2f}x | "
                     f"{r['transfers']['secondary']:,} / {r['transfers']['shadow']:,} | "
                     f"{r['render_s']:.2f} | {q['psnr_db']:.2f} | {q['ssim']:.4f} | "
                     f"{q['flip']:.4f} | {c.get('proxy_mispredictions', 0):,} / "
                     f"{c.get('proxy_uncertain', 0) + c.get('proxy_shadow_uncertain', 0):,} | "
                     f"{','.join(map(str, r['widths']))} | {r['proxy_bytes'] / 1e3:.0f} | "
                     f"{r['train_s']:.0f} |")
    return "\n".join(lines)


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(17, 5))
    panels = ((0, "total_bytes", "psnr", "ray MB sent", "PSNR vs exact (dB)"),
              (1, "total_bytes", "flip", "ray MB sent", "mean FLIP vs exact (lower is better)"),
              (2, "render_s", "psnr", "render wall time (s)", "PSNR vs exact (dB)"))
    for i, xkey, ykey, xlabel, ylabel in panels:
        ax = axes[i]
        scale = 1e6 if xkey == "total_bytes" else 1.0

        def y(r, ykey=ykey):
            q = r["quality_vs_exact"]
            return _psnr(q) if ykey == "psnr" else q["flip"]

        for knob in SWEEPS:
            rows = [r for r in res["points"] if r["knob"] == knob]
            xs, ys = [r[xkey] / scale for r in rows], [y(r) for r in rows]
            line, = ax.plot(xs, ys, "o-", label=knob, alpha=0.85)
            for r, xv, yv in zip(rows, xs, ys, strict=True):
                label = "cal" if r["value"] is None else f"{r['value']:g}"
                ax.annotate(label, (xv, yv), fontsize=6, color=line.get_color(),
                            xytext=(3, 3), textcoords="offset points")
        # The anchors' images equal exact (inf dB, FLIP 0): drawn as lines, not points,
        # so the axes zoom on the trade; exact sits far right, so it is only written.
        ora, ex = res["anchors"]["oracle"], res["anchors"]["exact"]
        ax.axvline(ora[xkey] / scale, color="k", ls=":", label="oracle (same image as exact)")
        unit = "MB" if xkey == "total_bytes" else "s"
        ax.text(0.98, 0.02, f"exact: {ex[xkey] / scale:.2f} {unit}", transform=ax.transAxes,
                ha="right", va="bottom", fontsize=8)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    s = res["settings"]
    fig.suptitle(f"proxy mode speed/accuracy: {res['scene']} ({res['size']}), K={s['shards']}, "
                 f"{s['width']}x{s['height']}, {s['spp']} spp; one knob at a time")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", choices=DEMOS, default="forest")
    ap.add_argument("--size", choices=["tiny", "small", "default"], default="default")
    ap.add_argument("--shards", type=int, default=4)
    ap.add_argument("--knobs", nargs="+", default=list(SWEEPS), choices=list(SWEEPS))
    ap.add_argument("--per-knob", type=int, default=None, help="only the first N values")
    add_render_flags(ap, RESULTS)
    args = smoke(ap.parse_args(argv), size="tiny", shards=2, width=16, spp=1, bounces=1,
                 shadow_rays=1, knobs=["band"], per_knob=1)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

    finish(run(args), args.out / f"proxy_sweep_{args.scene}_{args.size}.json", plot=plot,
           markdown=markdown, section="bench_proxy_sweep", readme=ROOT_README,
           update_readme=not args.no_readme,
           intro="### Speed against accuracy (proxy mode)\n\n"
                 f"`python -m bench.proxy.bench_proxy_sweep --scene {args.scene} --size "
                 f"{args.size}` (`{{json}}`):\n\n![]({{png}})\n\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
