"""Calibrating the step budget: held-out visibility accuracy of the old wall-clock-bounded
proxies (45 s each, ENCODING_VERSION 1) against step-bounded training at several budgets,
on the same held-out rays (seed + EVAL_SEED_OFFSET), mesh by mesh.

    python -m bench.proxy.bench_proxy_calibrate --old OLD_DIR --demos city --sizes small \
        --meshes twins hexa --steps 6000 12000 18000

    python -m bench.proxy.bench_proxy_calibrate --old OLD_DIR --table [NEW_DIR ...] proxies/shipped

OLD_DIR holds the old .nprx files (e.g. `git archive <commit> proxies/shipped`). A mesh is
measured at the widths its old proxies were trained at (--widths overrides). Every row is
appended to results/proxy_calibration.jsonl as it finishes, so a stopped run keeps what it
measured; wall and CPU seconds are reported with the load average (the machine is shared).
--table trains nothing: it prints, per demo mesh and width, the old proxy's held-out
accuracy beside the ones of the proxies in the given folders (their stored reports score the
same held-out rays, so the figures compare directly).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

from bench.common import RESULTS, smoke

SHIPPED = Path(__file__).resolve().parents[2] / "proxies" / "shipped"


def _old_proxies(old_dir: Path) -> dict:
    """{(content_hash, width): Proxy} of the .nprx files in a folder."""
    from nprt.proxies.inference import Proxy

    out = {}
    for f in sorted(old_dir.glob("*.nprx")):
        p = Proxy.from_bytes(f.read_bytes())
        out[(p.meta["content_hash"], int(p.meta["width"]))] = p
    return out


def _cell(p) -> str:
    """'accuracy (steps)' of a proxy's stored held-out report, '-' for none."""
    if p is None:
        return "-"
    r = p.meta["report"]
    return f"{r['accuracy']:.4f} ({r.get('vis_steps', 0) + r.get('depth_steps', 0)})"


def table(old: dict, new: list[tuple[str, dict]], demos, sizes) -> str:
    """Markdown: old against each new folder's held-out accuracy for every demo mesh (and
    width) any of them has; the last column is the last folder's change against old."""
    from nprt.scene.demos import DEMO_SIZES, make_demo

    heads = " | ".join(f"{label} acc (steps)" for label, _ in new)
    lines = [f"| demo | size | mesh | width | old acc (steps) | {heads} | change |",
             "| --- | --- | --- | ---: | ---: | " + "---: | " * len(new) + "---: |"]
    for demo in demos:
        for size in sizes:
            if size not in DEMO_SIZES[demo]:
                continue
            for mesh in make_demo(demo, size).meshes:
                h = mesh.content_hash
                widths = sorted({w for d in (old, *(n for _, n in new)) for k, w in d if k == h})
                for w in widths:
                    o, last = old.get((h, w)), new[-1][1].get((h, w))
                    cells = " | ".join(_cell(n.get((h, w))) for _, n in new)
                    d = (f"{last.meta['report']['accuracy'] - o.meta['report']['accuracy']:+.4f}"
                         if o and last else "")
                    lines.append(f"| {demo} | {size} | {mesh.name} | {w} | {_cell(o)} | "
                                 f"{cells} | {d} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.proxy.bench_proxy_calibrate",
                                 description=__doc__)
    ap.add_argument("--old", type=Path, help="folder of the old .nprx files (required)")
    ap.add_argument("--demos", nargs="+", default=["forest", "city", "sculpture"])
    ap.add_argument("--sizes", nargs="+", default=["default", "small", "tiny"])
    ap.add_argument("--meshes", nargs="*", default=None, help="mesh names (default: all)")
    ap.add_argument("--steps", nargs="*", type=int, default=[6000, 12000])
    ap.add_argument("--samples", nargs="*", type=int, default=[1 << 19],
                    help="training samples (ProxyConfig.n_samples)")
    ap.add_argument("--widths", nargs="*", type=int, default=None,
                    help="default: the widths of the mesh's old proxies")
    ap.add_argument("--out", type=Path, default=RESULTS / "proxy_calibration.jsonl")
    ap.add_argument("--table", type=Path, nargs="+", default=None, metavar="NEW_DIR",
                    help="print old against each NEW_DIR's proxies (no training)")
    ap.add_argument("--smoke", action="store_true",
                    help="one tiny mesh against the shipped proxies, 40 steps (CI smoke test)")
    args = smoke(ap.parse_args(argv), old=SHIPPED, demos=["forest"], sizes=["tiny"],
                 steps=[40], samples=[1 << 12], widths=[8])
    if args.old is None:
        ap.error("--old is required")
    if args.table is not None:
        new = [(d.name, _old_proxies(d)) for d in args.table]  # labelled by folder name
        print(table(_old_proxies(args.old), new, args.demos, args.sizes))
        return 0

    from nprt.proxies.config import EVAL_SEED_OFFSET, ProxyConfig
    from nprt.proxies.evaluate import evaluate
    from nprt.proxies.train import train_proxy
    from nprt.scene.demos import make_demo
    from nprt.workers.traversal.geometry import MeshGeometry

    old = _old_proxies(args.old)
    base = ProxyConfig()
    seed = base.seed + EVAL_SEED_OFFSET
    args.out.parent.mkdir(parents=True, exist_ok=True)
    for demo in args.demos:
        for size in args.sizes:
            scene = make_demo(demo, size)
            for mesh in scene.meshes:
                widths = args.widths or sorted(w for h, w in old if h == mesh.content_hash)
                if not widths or (args.meshes and mesh.name not in args.meshes):
                    continue
                geometry = MeshGeometry(mesh)
                for w in widths:
                    row = {"demo": demo, "size": size, "mesh": mesh.name,
                           "hash": mesh.content_hash[:10], "faces": len(mesh.faces), "width": w}
                    if (mesh.content_hash, w) in old:
                        p = old[(mesh.content_hash, w)]
                        rep = evaluate(p, mesh, base.eval_samples, seed, base.grid, geometry,
                                       speed=False)
                        r = p.meta.get("report", {})
                        row["old"] = {"accuracy": rep["accuracy"],
                                      "steps": (r.get("vis_steps"), r.get("depth_steps")),
                                      "train_s": r.get("train_s")}
                    for n in args.samples:
                        for steps in args.steps:
                            cfg = ProxyConfig(width=w, steps=steps, n_samples=n)
                            t0, c0 = time.perf_counter(), time.process_time()
                            p = train_proxy(mesh, cfg, progress=False, geometry=geometry)
                            row[f"new_{n}_{steps}"] = {
                                "accuracy": p.meta["report"]["accuracy"],
                                "train_s": round(p.timing["train_s"], 1),
                                "wall_s": round(time.perf_counter() - t0, 1),
                                "cpu_s": round(time.process_time() - c0, 1),
                                "load1": round(os.getloadavg()[0], 2)}
                    with args.out.open("a") as f:
                        f.write(json.dumps(row) + "\n")
                    print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
