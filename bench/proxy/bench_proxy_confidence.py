"""Accuracy where proxy mode trusts its proxies: for each proxy the policy ships at K = 4,
the share of held-out queries answered with confidence (|visibility - threshold| >= band)
and the accuracy on that share, as the band grows. The held-out accuracy the 97 % target
counts is the band-0 point; the renderer settles the rest exactly.

    python -m bench.proxy.bench_proxy_confidence [--scenes forest city sculpture family family@16]

A scene NAME@W forces width W on every mesh (the family's foliage meshes, which the policy
replicates, are then modelled too).

Nothing is trained (the shipped or cached proxies). Writes results/proxy_confidence.{json,png}
and a table into bench/README.md.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from bench.common import RESULTS, bench_scene, finish, smoke

BANDS = np.round(np.linspace(0.0, 0.5, 26), 3)
TABLE_BANDS = (0.0, 0.1, 0.2, 0.4)
TARGET = 0.97


def run(scenes: list[str], size: str, family_size: str) -> dict:
    from nprt.proxies.config import EVAL_SEED_OFFSET
    from nprt.proxies.evaluate import confidence_curve
    from nprt.proxies.sampling import sample_rays
    from nprt.scene.partition import partition
    from nprt.workers.runtime.pool import make_plan
    from nprt.workers.settings import RenderSettings

    out = {"bands": BANDS.tolist(), "default_band": RenderSettings().proxy.band, "meshes": []}
    for spec in scenes:
        name, _, width = spec.partition("@")
        settings = RenderSettings(shards=4, proxy={"width": int(width) if width else None})
        sz = family_size if name == "family" else size
        scene = bench_scene(name, sz)
        plan = make_plan(scene, partition(scene, 4), settings, train=False)
        for i, proxy in sorted(plan.proxies.items()):
            mesh = scene.meshes[i]
            cfg = proxy.meta["config"]
            held = sample_rays(mesh, cfg["eval_samples"], cfg["seed"] + EVAL_SEED_OFFSET,
                               cfg["grid"])
            curve = confidence_curve(proxy, held, proxy.meta["threshold"], BANDS)
            label = f"{name}:{sz}" + (f", width {width} forced" if width else "")
            out["meshes"].append({"scene": label, "mesh": mesh.name,
                                  "width": proxy.meta["width"], "curve": curve})
            at = {round(c["band"], 3): c for c in curve}
            print(f"{label} {mesh.name} w{proxy.meta['width']}: " + ", ".join(
                f"band {b}: {at[b]['share']:.3f} at {at[b]['accuracy']:.4f}"
                for b in TABLE_BANDS), flush=True)
    return out


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(m["scene"] for m in res["meshes"]))
    fig, axes = plt.subplots(1, len(scenes), figsize=(4.2 * len(scenes), 3.8), squeeze=False,
                             sharey=True)
    for ax, sc in zip(axes[0], scenes, strict=True):
        for m in (m for m in res["meshes"] if m["scene"] == sc):
            pts = [(c["share"], c["accuracy"]) for c in m["curve"] if c["accuracy"] is not None]
            line, = ax.plot(*zip(*pts, strict=True), lw=1.3, label=f"{m['mesh']} (w{m['width']})")
            d = next(c for c in m["curve"] if abs(c["band"] - res["default_band"]) < 1e-9)
            ax.plot(d["share"], d["accuracy"], "o", color=line.get_color(), ms=4)
        ax.axhline(TARGET, ls=":", color="k", lw=1)
        ax.set_title(sc)
        ax.set_xlabel("share of queries answered by the proxy")
        ax.invert_xaxis()
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, loc="lower left")
    axes[0][0].set_ylabel("held-out accuracy on that share")
    fig.suptitle(f"proxy accuracy where it is trusted: band 0 (left end) to 0.5; dots: the "
                 f"default band {res['default_band']}; dotted: {TARGET:.0%}")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def markdown(res: dict) -> str:
    head = " | ".join(f"band {b}: share / acc" for b in TABLE_BANDS)
    out = [f"| scene | mesh | width | {head} |", "| --- | --- | ---: |" + " ---: |" *
           len(TABLE_BANDS)]
    for m in res["meshes"]:
        at = {round(c["band"], 3): c for c in m["curve"]}
        cells = " | ".join(f"{at[b]['share']:.3f} / {at[b]['accuracy']:.4f}"
                           for b in TABLE_BANDS)
        out.append(f"| {m['scene']} | {m['mesh']} | {m['width']} | {cells} |")
    return "\n".join(out)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+",
                    default=["forest", "city", "sculpture", "family", "family@16"])
    ap.add_argument("--size", default="default", help="size of the demos")
    ap.add_argument("--family-size", default="small")
    ap.add_argument("--no-readme", action="store_true")
    ap.add_argument("--smoke", action="store_true",
                    help="the family scene alone, for the CI smoke test")
    args = smoke(ap.parse_args(argv), scenes=["family@16"])  # shipped: nothing to train
    res = run(args.scenes, args.size, args.family_size)
    finish(
        res, RESULTS / "proxy_confidence.json", plot=plot, markdown=markdown,
        section="bench_proxy_confidence", update_readme=not args.no_readme, intro=(
            "`python -m bench.proxy.bench_proxy_confidence` (`{json}`): "
            "each proxy the policy ships at K = 4 "
            f"(demos at `{args.size}`, the family scene at `{args.family_size}`), on its "
            "held-out rays. *share*: queries it answers itself (|visibility - threshold| >= "
            "band); *acc*: accuracy on those. Band 0 is the held-out accuracy of the 97 % "
            f"target; proxy mode's default band is {res['default_band']}.\n\n"
            "![]({png})\n\n"))


if __name__ == "__main__":
    main()
