"""`nprt demo`: the one command that shows what nprt does. Renders a demo scene with the
single-process reference and through the distributed path in each requested mode
(default `exact`, the Wald-style baseline, and `proxy`, the paper's method with the
shipped proxies; add `oracle` with --modes), same seed, then prints and saves the
comparison: transfers and bytes by kind, time, image quality against exact, and what the
proxy policy chose for each base mesh."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from nprt.workers.film import save_image


def cmd_demo(a) -> int:
    import ray

    from nprt.scene.store import open_scene
    from nprt.service.cli import render_with_progress, settings_from_args
    from nprt.workers.runtime.raysession import ensure_ray
    from nprt.workers.stats.quality import compare

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = open_scene(a.scene, size=a.size)  # metadata: the shards load the meshes
    print(f"scene {scene.name}: " + ", ".join(f"{k}={v:,}" for k, v in scene.summary().items()
                                              if isinstance(v, int)))
    started = ensure_ray(a.ray_address)
    runs = {}
    shards = a.shards
    try:
        for mode in ["reference", *a.modes]:
            a.mode, a.shards = ("exact", 0) if mode == "reference" else (mode, shards)
            settings = settings_from_args(a)
            res = render_with_progress(scene, settings, label=f"{mode} K={settings.shards}")
            res.film.save(out / f"{mode}.png")
            res.film.save(out / f"{mode}.exr")
            stats = res.stats_dict()
            (out / f"stats_{mode}.json").write_text(json.dumps(stats, indent=2, default=str))
            runs[mode] = (res.film.image(), stats)
    finally:
        if started:
            ray.shutdown()
    base_mode = "exact" if "exact" in runs else "reference"
    base = runs[base_mode][0]
    rows = {}
    for mode, (img, stats) in runs.items():
        rows[mode] = {"wall_s": stats["wall_s"], "transfers": stats["transfers"],
                      "bytes": stats["bytes"], "total_bytes": stats["total_bytes"],
                      "hops_histogram": stats["hops_histogram"], "phase_s": stats["phase_s"],
                      "counters": stats.get("counters", {}),
                      "proxy_plan": stats.get("proxy_plan"),
                      f"quality_vs_{base_mode}": compare(base, img)}
        if mode != base_mode:
            err = np.abs(img - base).mean(axis=2, keepdims=True).repeat(3, axis=2)
            save_image(np.concatenate([base, img, err * 4], axis=1),
                       out / f"{base_mode}_vs_{mode}_error.png")
    (out / "comparison.json").write_text(json.dumps({"scene": scene.summary(), "runs": rows},
                                                    indent=2, default=str))
    print(_table(rows, base_mode, shards))
    for mode, r in rows.items():
        if r["proxy_plan"]:
            print(f"\n{mode}: per base mesh\n" + _plan_table(r["proxy_plan"]))
    print(f"images, statistics and comparison in {out}/")
    return 0


def _table(rows: dict, base_mode: str, k: int) -> str:
    modes = list(rows)
    head = " | ".join(m if m == "reference" else f"{m} (K={k})" for m in modes)
    lines = [f"| | {head} |", "|---" * (len(modes) + 1) + "|"]
    for kind in ("primary", "secondary", "shadow"):
        lines.append(f"| {kind} transfers | " +
                     " | ".join(f"{r['transfers'][kind]:,}" for r in rows.values()) + " |")
    base_bytes = rows[base_mode]["total_bytes"]
    lines.append("| ray MB moved | " + " | ".join(
        f"{r['total_bytes'] / 1e6:.2f}" + (f" ({base_bytes / r['total_bytes']:.2f}x less)"
                                           if m != base_mode and r["total_bytes"] else "")
        for m, r in rows.items()) + " |")
    lines.append("| wall time (s) | " +
                 " | ".join(f"{r['wall_s']:.2f}" for r in rows.values()) + " |")
    q = [r[f"quality_vs_{base_mode}"] for r in rows.values()]
    lines.append(f"| PSNR dB / SSIM / FLIP vs {base_mode} | " + " | ".join(
        f"{x['psnr_db']:.2f} / {x['ssim']:.4f} / {x['flip']:.4f}" for x in q) + " |")
    lines.append("| mispredicted / uncertain secondary rays | " + " | ".join(
        f"{r['counters'].get('proxy_mispredictions', 0):,} / "
        f"{r['counters'].get('proxy_uncertain', 0):,}" if r["proxy_plan"] else ""
        for r in rows.values()) + " |")
    return "\n".join(lines)


def _plan_table(plan: dict) -> str:
    lines = ["| mesh | decision | width | held-out accuracy | proxy kB | why |",
             "|---|---|---:|---:|---:|---|"]
    for d in plan["decisions"]:
        acc = "" if d["accuracy"] is None else f"{d['accuracy']:.4f}"
        kb = "" if d["proxy_bytes"] is None else f"{d['proxy_bytes'] / 1e3:.1f}"
        lines.append(f"| {d['name']} | {d['decision']} | {d['width'] or ''} | {acc} | {kb} | "
                     f"{d['reason']} |")
    return "\n".join(lines)
