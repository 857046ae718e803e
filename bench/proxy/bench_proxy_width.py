"""What a proxy's width costs and buys at a job's accuracy target. Per scene and K: the
policy's plan (`nprt.proxies.policy`: the narrowest width meeting 97 %, else the narrowest
the most accurate does not lead by more than `Z_LEAD` standard errors) and each width
forced on every mesh (`ProxySettings.width`), rendered in proxy mode by the K shards in one
process (bench_visits.run: one thread, so process CPU is exact), against the exact render
at the same K and seed: CPU, the proxy phase, rays moved between shards, PSNR and SSIM.

The job's accuracy target (40 dB by default) picks every proxy's bands from its own
held-out error curve, so a narrower net that errs more sends more of its rays to exact
tracing: what width buys shows up as rays moved and CPU, not as error.

    python -m bench.proxy.bench_proxy_width --scenes /tmp/heldout/foliage.json forest --ks 2 8
    python -m bench.proxy.bench_proxy_width --smoke

Widths not cached are trained on first use (PyTorch); the shipped proxies cover the demos'
widths that the policy tried.
"""

from __future__ import annotations

import argparse
import os

import numpy as np

from bench.common import (
    add_image_flags,
    add_output_flags,
    finish,
    machine,
    quality,
    smoke,
    stored_scene,
)
from bench.render.bench_visits import run
from nprt.workers.runtime.placement import plan_placement
from nprt.workers.settings import ProxySettings, RenderSettings
from nprt.workers.wavefront.inprocess import shards_in_process

PLAN = "plan"


def _image(r: dict, s: RenderSettings) -> np.ndarray:
    """(h, w, 3) float32 mean radiance of a bench_visits.run film (summed samples)."""
    return (r["film"] / s.spp).reshape(s.height, s.width, 3).astype(np.float32)


def _widths(scene, s: RenderSettings) -> dict[str, int]:
    """mesh name -> width of every proxy in s's placement of scene (the proxies cached)."""
    return {scene.meshes[m].name: int(p.meta["width"])
            for m, p in plan_placement(scene, s).proxies.items()}


def bench(args) -> dict:
    rows = []
    for name in args.scenes:
        scene = stored_scene(name, args.size).load()
        for k in args.ks:
            base = dict(width=args.width, height=args.height, spp=args.spp, shards=k, seed=0)
            sx = RenderSettings(**base, mode="exact")
            ex = run(shards_in_process(scene, sx), sx)
            ref = _image(ex, sx)
            for w in args.widths:
                knobs = ProxySettings(accuracy=args.accuracy,
                                      width=None if w == PLAN else int(w))
                s = RenderSettings(**base, mode="proxy", proxy=knobs)
                r = run(shards_in_process(scene, s), s)
                q = quality(ref, _image(r, s))
                row = {"scene": name, "k": k, "width": w, "mesh_widths": _widths(scene, s),
                       "cpu_s": round(r["cpu_s"], 3), "exact_cpu_s": round(ex["cpu_s"], 3),
                       "proxy_s": round(r["phase_cpu_s"].get("proxy", 0.0), 3),
                       "rays_in": int(r["rays_in"]), "exact_rays_in": int(ex["rays_in"]),
                       "psnr_db": q["psnr_db"] if np.isfinite(q["psnr_db"]) else None,
                       "ssim": q["ssim"]}
                rows.append(row)
                print(_line(row), flush=True)
    return {"machine": machine(os.cpu_count()), "settings": vars(args) | {"out": str(args.out)},
            "rows": rows}


def _line(r: dict) -> str:
    return (f"{r['scene']} K={r['k']} width {r['width']} {r['mesh_widths']}: CPU "
            f"{r['cpu_s']:.2f} s = {r['cpu_s'] / r['exact_cpu_s']:.2f}x exact, proxy phase "
            f"{r['proxy_s']:.2f} s, rays moved {r['rays_in'] / r['exact_rays_in']:.2f}x "
            f"exact, PSNR {r['psnr_db']} dB")


def markdown(res: dict) -> str:
    out = ["Seconds of process CPU, the K shards in one process. *x exact*: against the "
           "exact render of the same K, image and seed; *rays moved*: rays a shard received "
           "from another; PSNR and SSIM against that exact render.", "",
           "| scene | K | width | widths per mesh | CPU s (x exact) | proxy phase s | rays moved "
           "(x exact) | PSNR dB | SSIM |", "|---|---:|---|---|---:|---:|---:|---:|---:|"]
    for r in res["rows"]:
        mw = ", ".join(f"{m} {w}" for m, w in sorted(r["mesh_widths"].items()))
        out.append(f"| {r['scene']} | {r['k']} | {r['width']} | {mw} | {r['cpu_s']:.2f} "
                   f"({r['cpu_s'] / r['exact_cpu_s']:.2f}x) | {r['proxy_s']:.2f} | "
                   f"{r['rays_in'] / 1e6:.2f} M ({r['rays_in'] / r['exact_rays_in']:.2f}x) | "
                   f"{r['psnr_db']} | {r['ssim']:.4f} |")
    return "\n".join(out) + "\n"


def plot(res: dict, png) -> None:
    """Per scene and K, CPU against exact (left) and PSNR against exact (right) by width."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    cases = sorted({(r["scene"], r["k"]) for r in res["rows"]}, key=str)
    for scene, k in cases:
        rows = [r for r in res["rows"] if (r["scene"], r["k"]) == (scene, k)]
        label = f"{os.path.basename(str(scene))} K = {k}"
        x = [str(r["width"]) for r in rows]
        a.plot(x, [r["cpu_s"] / r["exact_cpu_s"] for r in rows], "o-", label=label)
        b.plot(x, [r["psnr_db"] if r["psnr_db"] is not None else np.nan for r in rows], "o-",
               label=label)
    a.axhline(1.0, color="grey", lw=0.8)
    a.set(xlabel="proxy width (plan: the policy's choice per mesh)",
          ylabel="proxy CPU / exact CPU", title="What the nets cost")
    b.set(xlabel="proxy width", ylabel="PSNR against exact, dB",
          title=f"What they buy at the {res['settings']['accuracy']:g} dB target")
    a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.proxy.bench_proxy_width",
                                 description=__doc__.splitlines()[0])
    add_image_flags(ap)
    ap.set_defaults(scenes=["forest"])
    ap.add_argument("--ks", type=int, nargs="+", default=[2, 8])
    ap.add_argument("--widths", nargs="+", default=[PLAN, "16", "32", "64"],
                    choices=[PLAN, "16", "32", "64", "128", "256"])
    ap.add_argument("--accuracy", type=float, default=ProxySettings().accuracy,
                    help="the jobs' accuracy target, dB")
    add_output_flags(ap)
    args = smoke(ap.parse_args(argv), scenes=["forest"], width=32, height=24, spp=2, ks=[2],
                 widths=[PLAN, "16"])
    finish(bench(args), args.out / "bench_proxy_width.json", plot=plot, markdown=markdown,
           update_readme=False)


if __name__ == "__main__":
    main()
