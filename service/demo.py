"""`nprt demo`: the one command that shows what nprt does. Renders a demo scene through
the distributed path in `exact` (the Wald-style baseline) and `proxy` mode with the same
seed, then prints and saves the comparison: transfers, bytes, time and image error."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from workers.film import save_image


def _row(name: str, stats: dict) -> dict:
    return {"mode": name, "wall_s": stats["wall_s"], "transfers": stats["transfers"],
            "bytes": stats["bytes"], "total_bytes": stats["total_bytes"],
            "phase_s": stats["phase_s"], "counters": stats.get("counters", {})}


def cmd_demo(a) -> int:
    import ray

    from scene.io import load_any
    from service.cli import render_with_progress, settings_from_args
    from workers.coordinator import ensure_ray
    from workers.metrics import compare

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = load_any(a.scene, size=a.size)
    print(f"scene {scene.name}: " + ", ".join(f"{k}={v:,}" for k, v in scene.summary().items()
                                              if isinstance(v, int)))
    started = ensure_ray(a.ray_address)
    results = {}
    try:
        for mode in ("exact", "proxy"):
            a.mode = mode
            settings = settings_from_args(a)
            res = render_with_progress(scene, settings, label=f"{mode} K={settings.shards}")
            res.film.save(out / f"{mode}.png")
            res.film.save(out / f"{mode}.exr")
            stats = res.stats_dict()
            (out / f"stats_{mode}.json").write_text(json.dumps(stats, indent=2, default=str))
            results[mode] = (res.film.image(), stats)
    finally:
        if started:
            ray.shutdown()
    ref, ex = results["exact"]
    img, px = results["proxy"]
    quality = compare(ref, img)
    err = np.abs(img - ref).mean(axis=2)
    save_image(np.concatenate([ref, img, np.repeat(err[..., None], 3, 2) * 4], axis=1),
               out / "exact_proxy_error.png")
    summary = {"scene": scene.summary(), "exact": _row("exact", ex),
               "proxy": _row("proxy", px), "quality_vs_exact": quality,
               "proxy_plan": px.get("proxy_plan")}
    (out / "comparison.json").write_text(json.dumps(summary, indent=2, default=str))
    print(_table(ex, px, quality))
    print(f"images, statistics and comparison in {out}/")
    return 0


def _table(ex: dict, px: dict, q: dict) -> str:
    def ratio(a, b):
        return f"{a / b:.2f}x" if b else "n/a"

    lines = ["| | exact | proxy | exact / proxy |", "|---|---|---|---|"]
    for kind in ("primary", "secondary", "shadow"):
        e, p = ex["transfers"][kind], px["transfers"][kind]
        lines.append(f"| {kind} transfers | {e:,} | {p:,} | {ratio(e, p)} |")
    e, p = ex["total_bytes"], px["total_bytes"]
    lines.append(f"| ray bytes moved | {e:,} | {p:,} | {ratio(e, p)} |")
    lines.append(f"| wall time (s) | {ex['wall_s']:.2f} | {px['wall_s']:.2f} | "
                 f"{ratio(ex['wall_s'], px['wall_s'])} |")
    lines.append(f"| PSNR / SSIM / FLIP vs exact | | {q['psnr_db']:.2f} dB / {q['ssim']:.4f} / "
                 f"{q['flip']:.4f} | |")
    return "\n".join(lines)
