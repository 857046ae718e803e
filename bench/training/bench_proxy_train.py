"""Neural proxies of every demo base mesh (default size): training time, size, held-out
accuracy / false positives / false negatives / depth error, and onnxruntime queries/s,
for every width the policy tried (the chosen one marked).

    python -m bench.training.bench_proxy_train [--size default] [--target 0.97]
    python -m bench.training.bench_proxy_train --analytic   # encodings x widths on sphere/box/torus

Proxies come from the cache (user dir, then proxies/shipped/; missing ones are trained), so
training numbers are those recorded at training time; queries/s is re-measured on a batch of
65,536 rays with 1 and 2 onnxruntime threads. Writes bench/results/proxy_train_<size>.{json,md,png}.
"""

from __future__ import annotations

import argparse
import logging
import platform
from pathlib import Path

from bench.common import RESULTS, finish, smoke


def measure(size: str, target: float, train: bool) -> list[dict]:
    from nprt.proxies.cache import ProxyCache
    from nprt.proxies.config import DEFAULT_WIDTHS, ProxyConfig
    from nprt.proxies.evaluate import throughput
    from nprt.proxies.policy import plan_proxies
    from nprt.scene.demos import DEMOS, make_demo
    from nprt.scene.partition import partition

    cache, config, rows, seen = ProxyCache(), ProxyConfig(), [], set()
    for name in DEMOS:
        scene = make_demo(name, size=size)
        plan = plan_proxies(scene, partition(scene, 2), target, cache, train=train,
                            config=config, widths=DEFAULT_WIDTHS)
        for d in plan.decisions:
            mesh = scene.meshes[d.mesh]
            if d.decision not in ("proxy", "replicate") or not d.tried:
                rows.append({"scene": name, "mesh": d.name, "triangles": len(mesh.faces),
                             "mesh_bytes": d.mesh_bytes, "decision": d.decision,
                             "reason": d.reason})
                continue
            if mesh.content_hash in seen:
                continue
            seen.add(mesh.content_hash)
            for w in d.tried:
                p = cache.get(mesh, config.with_width(w))
                r = p.meta["report"]
                rows.append({
                    "scene": name, "mesh": d.name, "triangles": len(mesh.faces),
                    "mesh_bytes": d.mesh_bytes, "decision": d.decision,
                    "chosen": w == d.width, "width": w, "proxy_bytes": p.nbytes,
                    "accuracy": r["accuracy"], "fp_rate": r["fp_rate"],
                    "fn_rate": r["fn_rate"], "hit_fraction": r["hit_fraction"],
                    "depth_err_rel": r["depth_err_rel"],
                    "internal_occlusion_accuracy": r["internal_occlusion_accuracy"],
                    "train_s": r["train_s"], "vis_steps": r["vis_steps"],
                    "depth_steps": r["depth_steps"], "threshold": p.meta["threshold"],
                    "qps_1thread": throughput(p, threads=1),
                    "qps_2threads": throughput(p, threads=2),
                })
    return rows


ANALYTIC_BUDGET = dict(steps=3334, n_samples=1 << 19, grid=64,
                       eval_samples=1 << 15)
ENCODINGS = {"line+fourier3 (default)": dict(encoding="line", fourier=3),
             "paper (theta/pi, phi/2pi)": dict(encoding="paper", fourier=0),
             "paper+fourier3": dict(encoding="paper", fourier=3)}


def measure_analytic(widths=(16, 32, 64)) -> list[dict]:
    """Sphere, box, torus at a fixed step budget: encodings x widths, same seeds."""
    import trimesh

    from nprt.proxies.config import ProxyConfig
    from nprt.proxies.evaluate import throughput
    from nprt.proxies.train import train_proxy
    from nprt.scene.model import Mesh

    shapes = {"sphere": trimesh.creation.icosphere(subdivisions=3),
              "box": trimesh.creation.box(extents=(1.0, 0.6, 0.8)),
              "torus": trimesh.creation.torus(1.0, 0.3)}
    rows = []
    for name, tm in shapes.items():
        mesh = Mesh(name, tm.vertices.astype("float32"), tm.faces.astype("uint32"))
        for enc, kw in ENCODINGS.items():
            for w in widths:
                p = train_proxy(mesh, ProxyConfig(width=w, **kw, **ANALYTIC_BUDGET),
                                progress=False)
                r = p.meta["report"]
                rows.append({"mesh": name, "encoding": enc, "width": w, "bytes": p.nbytes,
                             **{k: r[k] for k in ("accuracy", "fp_rate", "fn_rate",
                                                  "depth_err_rel", "train_s",
                                                  "internal_occlusion_accuracy")},
                             "qps_1thread": throughput(p, threads=1),
                             "qps_2threads": throughput(p, threads=2)})
                print(rows[-1], flush=True)
    return rows


def markdown_analytic(rows: list[dict]) -> str:
    out = ["| mesh | encoding | width | acc | FP | FN | depth err | internal acc | bytes | "
           "Mq/s 1t | Mq/s 2t |", "|" + "---|" * 11]
    for r in rows:
        out.append(f"| {r['mesh']} | {r['encoding']} | {r['width']} | {r['accuracy']:.4f} | "
                   f"{r['fp_rate']:.4f} | {r['fn_rate']:.4f} | {100 * r['depth_err_rel']:.2f}% "
                   f"| {r['internal_occlusion_accuracy']:.4f} | {r['bytes']} | "
                   f"{r['qps_1thread'] / 1e6:.2f} | {r['qps_2threads'] / 1e6:.2f} |")
    return "\n".join(out)


def markdown(rows: list[dict]) -> str:
    head = ("| scene | mesh | tris | width | acc | FP | FN | depth err | internal acc | bytes | "
            "train s | Mq/s 1t | Mq/s 2t |")
    out = [head, "|" + "---|" * 13]
    for r in rows:
        if "width" not in r:
            out.append(f"| {r['scene']} | {r['mesh']} | {r['triangles']} | {r['decision']} "
                       f"| | | | | | {r['mesh_bytes']} | | | |")
            continue
        w = f"**{r['width']}**" if r["chosen"] else str(r["width"])
        out.append(
            f"| {r['scene']} | {r['mesh']} | {r['triangles']} | {w} | {r['accuracy']:.4f} | "
            f"{r['fp_rate']:.4f} | {r['fn_rate']:.4f} | {100 * r['depth_err_rel']:.2f}% | "
            f"{r['internal_occlusion_accuracy']:.4f} | {r['proxy_bytes']} | "
            f"{r['train_s']:.0f} | {r['qps_1thread'] / 1e6:.2f} | {r['qps_2threads'] / 1e6:.2f} |")
    return "\n".join(out)


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in rows if "width" in r]
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for mesh in dict.fromkeys(f"{r['scene']}/{r['mesh']}" for r in rows):
        rs = [r for r in rows if f"{r['scene']}/{r['mesh']}" == mesh]
        a.plot([r["width"] for r in rs], [r["accuracy"] for r in rs], "o-", label=mesh)
    widths = sorted({r["width"] for r in rows})
    qps = [max(r["qps_1thread"] for r in rows if r["width"] == w) / 1e6 for w in widths]
    b.bar([str(w) for w in widths], qps)
    a.set_xscale("log", base=2)
    a.set(xlabel="width N", ylabel="held-out visibility accuracy",
          title="accuracy by width (default CPU budget)")
    a.set_xticks(widths, [str(w) for w in widths])
    a.minorticks_off()
    a.legend(fontsize=6, ncol=2)
    b.set(xlabel="width N", ylabel="M queries/s (1 thread, best mesh)",
          title="onnxruntime proxy queries/s")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.training.bench_proxy_train")
    ap.add_argument("--size", default="default")
    ap.add_argument("--target", type=float, default=0.97)
    ap.add_argument("--no-train", action="store_true", help="only use cached proxies")
    ap.add_argument("--analytic", action="store_true",
                    help="instead: sphere/box/torus, encodings x widths at a fixed step budget")
    ap.add_argument("--smoke", action="store_true",
                    help="the tiny demos, cached proxies only, for the CI smoke test")
    args = smoke(ap.parse_args(argv), size="tiny", no_train=True)
    logging.basicConfig(level=logging.WARNING)
    if args.analytic:
        rows = measure_analytic()
        path = RESULTS / "proxy_train_analytic.json"
        finish({"budget": ANALYTIC_BUDGET, "rows": rows}, path,
               markdown=lambda r: markdown_analytic(rows), table_file=True)
        return 0
    rows = measure(args.size, args.target, not args.no_train)
    path = RESULTS / f"proxy_train_{args.size}.json"
    meta = {"size": args.size, "target": args.target, "machine": platform.processor()
            or platform.machine(), "python": platform.python_version()}
    finish({**meta, "rows": rows}, path, plot=lambda r, png: plot(rows, png),
           markdown=lambda r: markdown(rows), table_file=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
