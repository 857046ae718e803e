"""The confidence band on every demo: PSNR, SSIM and FLIP against exact at the same seed,
ray bytes and secondary transfers (against the oracle's) as the band of secondary rays
widens, with shadow rays decided where they are made (shadow band 0, the paper's rule).
It is the measurement behind ProxySettings.band's default.

    python -m bench.proxy.bench_proxy_band [--scenes forest,city,sculpture,windy] [--shards 4]

Writes results/proxy_band_<size>.{json,png} and a section of bench/README.md.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

import ray
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from bench.common import (
    RESULTS,
    add_render_flags,
    finish,
    machine,
    quality,
    render_settings,
    smoke,
    start_ray,
    timed_render,
)
from bench.proxy.bench_proxies import TARGETS
from nprt.scene.demos import DEMOS, make_demo
from nprt.workers.settings import ProxySettings

BANDS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5)
PSNR_TARGET = TARGETS["psnr_db_k4"]


def run(args) -> dict:
    base = render_settings(args, shards=args.shards)
    names = [n for n in args.scenes.split(",") if n]
    start_ray(args.shards)
    out = {"size": args.size, "settings": base.model_dump(), "bands": args.bands,
           "default_band": ProxySettings().band, "machine": machine(args.shards),
           "scenes": {}}
    columns = (TextColumn("{task.description:<24}"), BarColumn(), MofNCompleteColumn(),
               TimeElapsedColumn())
    try:
        with Progress(*columns) as bar:
            task = bar.add_task("renders", total=len(names) * (2 + len(args.bands)))
            for name in names:
                scene = make_demo(name, args.size)
                sc = out["scenes"][name] = {"points": []}
                anchors = {}
                for mode in ("exact", "oracle"):
                    bar.update(task, description=f"{name} {mode}")
                    anchors[mode] = timed_render(scene, base.model_copy(update={"mode": mode}))
                    bar.advance(task)
                ex_row, ex_img, _ = anchors["exact"]
                sc["exact"], sc["oracle"] = ex_row, anchors["oracle"][0]
                for band in args.bands:
                    bar.update(task, description=f"{name} band {band}")
                    s = base.model_copy(update={"mode": "proxy",
                                                "proxy": ProxySettings(band=band)})
                    row, img, _ = timed_render(scene, s)
                    row.update(band=band, quality_vs_exact=quality(ex_img, img))
                    sc["points"].append(row)
                    bar.advance(task)
        out["machine"]["load_average_after"] = os.getloadavg()
    finally:
        ray.shutdown()
    return out


def markdown(res: dict) -> str:
    s = res["settings"]
    lines = [f"Size `{res['size']}`, K={s['shards']}, {s['width']}x{s['height']}, {s['spp']} "
             f"spp, {s['bounces']} bounces, {s['shadow_rays']} shadow rays, seed {s['seed']}; "
             "shadow band 0, thresholds calibrated per proxy, the shipped proxies; "
             f"{res['machine']['cpus']} cores. Quality is against exact at the same seed; "
             "bytes are ray batches sent between shards. The default band is "
             f"{res['default_band']}.", "",
             "| scene | band | PSNR dB | SSIM | FLIP | bytes vs exact | secondary transfers "
             "vs oracle | mispredicted / uncertain secondary | render s |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: |"]
    for name, sc in res["scenes"].items():
        ex, ora = sc["exact"], sc["oracle"]
        for r in sc["points"]:
            q, c = r["quality_vs_exact"], r["counters"]
            mark = " (default)" if r["band"] == res["default_band"] else ""
            psnr = f"**{q['psnr_db']:.2f}**" if q["psnr_db"] >= PSNR_TARGET else \
                f"{q['psnr_db']:.2f}"
            lines.append(
                f"| {name} | {r['band']}{mark} | {psnr} | {q['ssim']:.4f} | {q['flip']:.4f} | "
                f"{ex['total_bytes'] / max(r['total_bytes'], 1):.2f}x | "
                f"{r['transfers']['secondary'] / max(ora['transfers']['secondary'], 1):.2f}x | "
                f"{c.get('proxy_mispredictions', 0):,} / {c.get('proxy_uncertain', 0):,} | "
                f"{r['render_s']:.2f} |")
    lines += ["", f"PSNR at or above the {PSNR_TARGET:g} dB target is in bold."]
    return "\n".join(lines)


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for name, sc in res["scenes"].items():
        ex = sc["exact"]["total_bytes"]
        bands = [r["band"] for r in sc["points"]]
        psnr = [r["quality_vs_exact"]["psnr_db"] for r in sc["points"]]
        ratio = [ex / max(r["total_bytes"], 1) for r in sc["points"]]
        axes[0].plot(bands, psnr, "o-", label=name)
        line, = axes[1].plot(ratio, psnr, "o-", label=name)
        for b, x, y in zip(bands, ratio, psnr, strict=True):
            axes[1].annotate(f"{b:g}", (x, y), fontsize=7, color=line.get_color(),
                             xytext=(3, 3), textcoords="offset points")
    for ax in axes:
        ax.axhline(PSNR_TARGET, color="k", ls=":", lw=1)
        ax.set_ylabel("PSNR vs exact (dB)")
        ax.grid(alpha=0.3)
    axes[0].axvline(res["default_band"], color="gray", ls="--", lw=1, label="default")
    axes[0].set_xlabel("confidence band (secondary rays)")
    axes[1].set_xlabel("ray bytes, exact / proxy (higher: fewer bytes)")
    axes[0].legend(fontsize=8)
    s = res["settings"]
    fig.suptitle(f"proxy confidence band, demos ({res['size']}), K={s['shards']}, "
                 f"{s['width']}x{s['height']}, {s['spp']} spp; dotted: {PSNR_TARGET:g} dB")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.proxy.bench_proxy_band",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default=",".join(DEMOS))
    ap.add_argument("--size", choices=["tiny", "small", "default"], default="default")
    ap.add_argument("--shards", type=int, default=4)
    ap.add_argument("--bands", type=float, nargs="+", default=list(BANDS))
    add_render_flags(ap, RESULTS)
    args = smoke(ap.parse_args(argv), scenes="forest", size="tiny", shards=2, width=16, spp=1,
                 bounces=1, shadow_rays=1, bands=[0.4])
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    finish(run(args), args.out / f"proxy_band_{args.size}.json", plot=plot, markdown=markdown,
           section="bench_proxy_band", update_readme=not args.no_readme,
           intro="## Confidence band (`bench_proxy_band.py`)\n\n"
                 f"`python -m bench.proxy.bench_proxy_band --size {args.size}` "
                 "(`{json}`):\n\n![]({png})\n\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
