"""What lifts held-out visibility accuracy per CPU-second on thin and foliage-like meshes:
training variants against the default config, on the test family (scene/demos/family.py)
and the forest's pine, at equal step budgets, same seeds. Training is deterministic, so
accuracy is exact run to run; CPU seconds (process time of training + sampling) vary with
the load and are quoted with it.

    python -m bench.experiments.bench_proxy_thin [--steps 1000] [--size tiny]

Writes bench/results/proxy_thin_<size>.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace

from bench.common import RESULTS, finish, smoke

# One change at a time against the base config; "steps x3" is the plain budget knob.
VARIANTS = {
    "default (line+fourier3, natural hit share)": {},
    "steps x3": {"steps": 3},
    "batch 1024, steps x4 (same rays seen)": {"batch_size": 1024, "steps": 4},
    "hit share 0.5": {"hit_share": 0.5},
    "fourier 0 (raw line)": {"fourier": 0},
    "fourier 5": {"fourier": 5},
    "paper encoding (direct, no fourier)": {"encoding": "paper", "fourier": 0},
    "lr 5e-3": {"lr": 5e-3},
    "samples /4": {"n_samples": 0.25},
    "width 32": {"width": 32},
}
SCALED = ("steps", "n_samples")  # variant values that multiply the base instead of replacing


def meshes(size: str):
    from nprt.scene.demos import make_demo
    from nprt.scene.demos.family import family_meshes

    fam = {m.name: m for m in family_meshes(size)}
    forest = {m.name: m for m in make_demo("forest", size).meshes}
    return [fam["foliage"], fam["holes"], fam["rings"], forest["pine"]]


def run(steps: int, size: str, samples: int = 1 << 17, variants=tuple(VARIANTS)) -> list[dict]:
    from nprt.proxies.config import ProxyConfig
    from nprt.proxies.train import train_proxy

    base = ProxyConfig(width=16, steps=steps, n_samples=samples, grid=32, eval_samples=1 << 15)
    rows = []
    for mesh in meshes(size):
        for name in variants:
            change = VARIANTS[name]
            kw = {k: (int(v * getattr(base, k)) if k in SCALED else v)
                  for k, v in change.items()}
            cfg = replace(base, **kw)
            t0, c0 = time.perf_counter(), time.process_time()
            p = train_proxy(mesh, cfg, progress=False)
            r = p.meta["report"]
            rows.append({"mesh": mesh.name, "triangles": len(mesh.faces), "variant": name,
                         "accuracy": r["accuracy"], "fp_rate": r["fp_rate"],
                         "fn_rate": r["fn_rate"],
                         "internal_acc": r["internal_occlusion_accuracy"],
                         "train_cpu_s": time.process_time() - c0,
                         "wall_s": time.perf_counter() - t0, "train_s": p.timing["train_s"],
                         "load": os.getloadavg()[0]})
            print(json.dumps(rows[-1]), flush=True)
    return rows


def markdown(rows: list[dict]) -> str:
    out = ["| mesh | variant | accuracy | FP | FN | internal acc | CPU s | load |",
           "|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        out.append(f"| {r['mesh']} ({r['triangles']} tris) | {r['variant']} | "
                   f"{r['accuracy']:.4f} | {r['fp_rate']:.4f} | {r['fn_rate']:.4f} | "
                   f"{r['internal_acc']:.4f} | {r['train_cpu_s']:.1f} | {r['load']:.1f} |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.experiments.bench_proxy_thin")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--size", default="tiny", choices=["tiny", "small", "default"])
    ap.add_argument("--samples", type=int, default=1 << 17, help="training rays (base config)")
    ap.add_argument("--smoke", action="store_true",
                    help="the default variant, 20 steps on 4096 rays, for the CI smoke test")
    args = smoke(ap.parse_args(argv), steps=20, samples=1 << 12)
    rows = run(args.steps, args.size, args.samples,
               list(VARIANTS)[:1] if args.smoke else tuple(VARIANTS))
    path = RESULTS / f"proxy_thin_{args.size}.json"
    finish({"steps": args.steps, "rows": rows}, path, markdown=lambda r: markdown(rows),
           table_file=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
