"""Strong scaling: one image, more shards. The 1-core single-process reference against
exact and proxy mode at K = 1, 2, 4, 8, ... (up to the machine's cores minus two), side by
side in one run, on whatever cores this machine has.

Per row: render wall (the pool already started; its start is `prepare_s`), CPU seconds per
shard and in total (process CPU of every shard plus the coordinator's), coordinator CPU,
busy fraction, the share of shard CPU in named phases and outside the wavefront thread
(Ray's own threads), the local raylet's CPU during the render (the object store's work for
parcels above the inline limit: not in the total, which is the issue's "all shards plus
the coordinator"), wavefront steps, parcels, ray bytes, and PSNR of proxy against exact at
the same K.

Where the machine has fewer cores than K + 1, the walls measure oversubscription. So every
distributed run also records its step trace, and bench/network/netmodel.py replays it on K
dedicated cores (each step takes its own recorded CPU seconds, parcels cross links of
MODEL_LINK_BPS, one free parameter: the coordinator's one-way latency, fitted on this run's
K = 1 renders, where one shard and the coordinator each had a core). The model's wall is
compared with the reference's CPU seconds (its wall on a dedicated core).

    python -m bench.render.bench_strong_scaling                      # forest, city; 640x360 16 spp
    python -m bench.render.bench_strong_scaling --scenes forest --ks 1 2 --width 320 --spp 4
    python -m bench.render.bench_strong_scaling --smoke              # CI: tiny, no README
    python -m bench.render.bench_strong_scaling --merge A.json B.json --tag T  # one table

Runs cut to fit a short lease (a lent many-core machine) are merged afterwards with
`--merge`: their rows, each tagged with its run, in one table and one plot (each row's
ratios stay against the reference of its own run).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
from pathlib import Path

import numpy as np

from bench.common import (
    add_byte_slack_flag,
    add_image_flags,
    add_output_flags,
    finish,
    fmt_or_blank,
    machine,
    placeable_ks,
    quality,
    smoke,
    stored_scene,
    timed_render,
)
from bench.network.netmodel import film_bytes, fit_rpc_s, replay, step_cpu
from nprt.workers.settings import SPP_PER_PASS, RenderSettings

TARGETS = {"proxy_k8_wall": 0.3, "exact_k8_wall": 0.5, "proxy_cpu": 2.0, "exact_cpu": 3.0,
           "coordinator_cpu_share": 0.05, "exact_k2_wall_2core": 0.8, "proxy_k2_wall_2core": 0.65}
MODEL_LINK_BPS = 25e9  # the model's links: a cluster's network (one host's object store is faster)
FALLBACK_RPC_S = 0.0057  # coordinator latency when no K = 1 run fits it (bench_network's)


def _cpuinfo(key: str) -> str | None:
    """The first value of `key` in /proc/cpuinfo, or None."""
    try:
        for line in open("/proc/cpuinfo"):
            if line.split(":", 1)[0].strip() == key:
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return None


def cpu_model() -> str:
    return _cpuinfo("model name") or platform.processor() or "unknown"


def threads_per_core() -> float | None:
    """Hardware threads per physical core (2 where `nproc` counts hyperthreads: K shards on
    K such "cores" share execution units, and the 1-core reference ran on a whole core)."""
    siblings, cores = _cpuinfo("siblings"), _cpuinfo("cpu cores")
    return int(siblings) / int(cores) if siblings and cores else None


def run_one(scene, s: RenderSettings) -> tuple[dict, np.ndarray, dict | None]:
    """Prepare a renderer (pool start or reference set-up), then one timed render. Returns
    (row, image, model input: trace, window and film bytes; None for the reference)."""
    base, image, info = timed_render(scene, s, trace=True)
    shards = info.get("shard_stats", [])
    row = {**{k: base[k] for k in ("mode", "k", "prepare_s", "render_s", "phase_cpu_s")},
           "cpu_s": info.get("cpu_s"),
           "coordinator_cpu_s": info.get("coordinator_cpu_s", 0.0),
           "shard_cpu_s": [x["cpu_s"] for x in shards],
           "wavefront_cpu_s": [x["wavefront_cpu_s"] for x in shards],
           "busy_fraction": [x["busy_fraction"] for x in shards],
           "named_cpu_fraction": [x["cpu_named_fraction"] for x in shards],
           "steps": sum(x["steps"] for x in shards), "parcels": sum(x["calls"] for x in shards),
           "ray_bytes": base["total_bytes"], "transfers": base["total_transfers"],
           "raylet_cpu_s": base["raylet_cpu_s"]}
    run = ({"trace": info["trace"], "window": info["window"], "film_bytes": film_bytes(s),
            "wall_s": row["render_s"]} if "trace" in info else None)
    return row, image, run


def model_walls(rows: list[dict], runs: list[dict], ref_cpu_s: float, cores: int) -> dict:
    """Replay each distributed row's trace on K dedicated cores (adds model_render_s and
    model_ratio, against the reference's CPU seconds, to each row). The coordinator latency
    is fitted on the K = 1 rows; rows with K + 1 <= cores (a core each, the coordinator's
    too) are where the model can be checked against the measured wall."""
    ones = [(r["trace"], MODEL_LINK_BPS, r["wall_s"], r["window"], r["film_bytes"])
            for row, r in zip(rows, runs, strict=True) if row["k"] == 1]
    rpc_s, fit_err = fit_rpc_s(ones) if ones else (FALLBACK_RPC_S, None)
    checks = []
    for row, r in zip(rows, runs, strict=True):
        rep = replay(r["trace"], MODEL_LINK_BPS, rpc_s, r["window"], r["film_bytes"],
                     step_cpu(r["trace"]))
        row["model_render_s"] = round(rep.makespan_s, 3)
        row["model_ratio"] = round(rep.makespan_s / ref_cpu_s, 3)
        if row["k"] + 1 <= cores:
            checks.append({"mode": row["mode"], "k": row["k"], "measured_s": row["render_s"],
                           "model_s": row["model_render_s"], "fitted": row["k"] == 1,
                           "error": round(rep.makespan_s / row["render_s"] - 1, 4)})
    return {"rpc_s": rpc_s, "fit_log_error": fit_err, "link_bps": MODEL_LINK_BPS,
            "checks": checks}


def bench(args) -> dict:
    rows, models = [], {}
    for name in args.scenes:
        scene = stored_scene(name, args.size)
        base = dict(width=args.width, height=args.height, spp=args.spp, seed=0,
                    spp_per_pass=args.spp_per_pass, byte_slack=args.byte_slack)
        loaded = scene.load()
        ref, ref_img, _ = run_one(loaded, RenderSettings(**base, shards=0))
        ref.update(scene=name, wall_ratio=1.0, cpu_ratio=1.0)
        rows.append(ref)
        print(_line(ref), flush=True)
        dist, runs = [], []
        for k in placeable_ks(args.ks, loaded, name):
            exact_img = None
            for mode in args.modes:
                row, img, run = run_one(scene, RenderSettings(**base, shards=k, mode=mode))
                row.update(scene=name, coordinator_share=round(row["coordinator_cpu_s"]
                                                               / row["cpu_s"], 4))
                _ratios(row, ref)
                if mode == "exact":
                    exact_img = img
                    row["psnr_vs_reference_db"] = quality(ref_img, img)["psnr_db"]
                elif exact_img is not None:
                    row["psnr_vs_exact_db"] = quality(exact_img, img)["psnr_db"]
                rows.append(row)
                dist.append(row)
                runs.append(run)
                print(_line(row), flush=True)
                _partial(args, rows)
        # The reference again after the distributed runs: on a lent machine its wall moved
        # 13-20 % within one lease. The ratios are then against the mean of its runs.
        again = [run_one(loaded, RenderSettings(**base, shards=0))[0]
                 for _ in range(args.ref_runs - 1)]
        if again:
            _bracket(ref, again)
            for row in dist:
                _ratios(row, ref)
            print(f"{name} reference runs {ref['render_s_runs']} s (CPU {ref['cpu_s_runs']} s):"
                  f" ratios against their means", flush=True)
        models[name] = model_walls(dist, runs, ref["cpu_s"], os.cpu_count() or 1)
        del runs  # traces of a large K run to tens of MB
        for row in dist:
            print(f"{name} {row['mode']:9s} K={row['k']:2d} model on K dedicated cores "
                  f"{row['model_render_s']:7.2f} s = {row['model_ratio']:.2f}x the reference's "
                  "CPU", flush=True)
    return {"machine": {**machine(os.cpu_count()), "nproc": os.cpu_count(),
                        "cpu_model": cpu_model(), "threads_per_core": threads_per_core()},
            "settings": vars(args) | {"out": str(args.out)}, "targets": TARGETS, "rows": rows,
            "model": models}


def _ratios(row: dict, ref: dict) -> None:
    row.update(wall_ratio=round(row["render_s"] / ref["render_s"], 3),
               cpu_ratio=round(row["cpu_s"] / ref["cpu_s"], 3))


def _bracket(ref: dict, again: list[dict]) -> None:
    """The reference row's render_s and cpu_s become the means over its first run and the
    runs `again`, each run's kept in render_s_runs and cpu_s_runs."""
    for key in ("render_s", "cpu_s"):
        values = [ref[key]] + [r[key] for r in again]
        ref[f"{key}_runs"] = values
        ref[key] = round(sum(values) / len(values), 4)


def _partial(args, rows: list[dict]) -> None:
    """Rows so far, so a run cut short by a time limit still leaves them."""
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "strong_scaling_partial.json").write_text(json.dumps(rows, indent=1))


def _line(r: dict) -> str:
    return (f"{r['scene'] if 'scene' in r else ''} {r['mode']:9s} K={r['k']:2d} "
            f"render {r['render_s']:7.2f} s  cpu {r['cpu_s']:7.2f} s  "
            f"coord {r['coordinator_cpu_s']:.2f} s  bytes {r['ray_bytes'] / 1e6:.1f} MB")


def markdown(res: dict) -> str:
    m = res["machine"]
    tpc = m.get("threads_per_core")
    runs = any("run" in r for r in res["rows"])  # merged runs: each row says its own
    out = [f"Machine: {m['nproc']} cores ({m['cpu_model']}"
           + (f", {tpc:g} hardware threads per physical core" if tpc else "")
           + f"), Ray {m['ray']}.", "",
           ("| run " if runs else "") + "| scene | renderer | K | render s | vs reference | "
           "CPU s (all) | CPU vs ref | "
           "coordinator CPU s (share) | shard CPU s | busy | named CPU | Ray threads | "
           "raylet CPU s | steps | parcels | ray MB | PSNR dB | model s, K cores | model vs ref |",
           ("|---" if runs else "") + "|---|---|---:|---:|---:|---:|---:|---:|---|---|---:|"
           "---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in res["rows"]:
        named = [x for x in r["named_cpu_fraction"] if x is not None]
        psnr = r.get("psnr_vs_exact_db", r.get("psnr_vs_reference_db", ""))
        out.append(
            (f"| {r.get('run', '')} " if runs else "")
            + f"| {r['scene']} | {r['mode']} | {r['k']} | {r['render_s']:.2f} | "
            f"{r['wall_ratio']:.2f}x | {r['cpu_s']:.1f} | {r['cpu_ratio']:.2f}x | "
            f"{r['coordinator_cpu_s']:.2f} ({100 * r.get('coordinator_share', 0):.1f} %) | "
            f"{', '.join(f'{c:.1f}' for c in r['shard_cpu_s'])} | "
            f"{', '.join(f'{b:.2f}' for b in r['busy_fraction'])} | "
            f"{min(named) if named else 1.0:.3f} | {_ray_threads(r)} | "
            f"{fmt_or_blank(r.get('raylet_cpu_s'), '.2f')} | {r['steps']} | "
            f"{r['parcels']} | "
            f"{r['ray_bytes'] / 1e6:.1f} | {psnr if psnr != '' else ''} | "
            f"{fmt_or_blank(r.get('model_render_s'), '.2f')} | "
            f"{fmt_or_blank(r.get('model_ratio'), '.2f', 'x')} |")
    bracketed = [r for r in res["rows"] if "render_s_runs" in r]
    if bracketed:
        out += ["", "The reference rows are means over runs before and after the distributed "
                "ones: " + "; ".join(
                    f"{r['scene']} {', '.join(f'{w:.2f}' for w in r['render_s_runs'])} s"
                    for r in bracketed) + "."]
    for name, m in res.get("model", {}).items():
        checks = ", ".join(f"{c['mode']} K={c['k']} {c['measured_s']:.2f} s measured, "
                           f"{c['model_s']:.2f} s model ({100 * c['error']:+.0f} %"
                           f"{', fitted' if c['fitted'] else ''})" for c in m["checks"])
        fitted = "fitted on the K = 1 runs" if m["fit_log_error"] is not None else "not fitted"
        out += ["", f"Model ({name}): coordinator latency {1e3 * m['rpc_s']:.1f} ms one way "
                    f"({fitted}), "
                    f"links {m['link_bps'] / 1e9:.0f} Gbit/s. Against the walls measured where "
                    f"each shard and the coordinator had a core: {checks or 'none'}."]
    return "\n".join(out)


def _ray_threads(r: dict) -> str:
    """Share of the shards' process CPU outside the wavefront thread (Ray's own threads:
    deliveries, polls, object transfers); blank for the reference and older results."""
    wave, cpu = r.get("wavefront_cpu_s"), sum(r["shard_cpu_s"])
    return "" if not wave or not cpu else f"{1 - sum(wave) / cpu:.2f}"


def plot(res: dict, png) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = sorted({r["scene"] for r in res["rows"]})
    fig, axes = plt.subplots(2, len(scenes), figsize=(5 * len(scenes), 7), squeeze=False)
    for j, name in enumerate(scenes):
        rows = [r for r in res["rows"] if r["scene"] == name]
        for mode, style, color in (("exact", "o-", "C0"), ("proxy", "s-", "C2")):
            rs = sorted((r for r in rows if r["mode"] == mode), key=lambda r: r["k"])
            if rs:
                ks = [r["k"] for r in rs]
                axes[0, j].plot(ks, [r["wall_ratio"] for r in rs], style, color=color,
                                label=mode)
                if all("model_ratio" in r for r in rs):
                    axes[0, j].plot(ks, [r["model_ratio"] for r in rs], style[0] + "--",
                                    color=color, alpha=0.5, label=f"{mode}, model on K cores")
                axes[1, j].plot(ks, [r["cpu_ratio"] for r in rs], style, color=color,
                                label=mode)
        t = res.get("targets", TARGETS)
        for i, (what, lines) in enumerate((
                ("render wall / 1-core reference", (("exact K = 8", t["exact_k8_wall"]),
                                                    ("proxy K = 8", t["proxy_k8_wall"]))),
                ("total CPU / reference CPU", (("exact", t["exact_cpu"]),
                                               ("proxy", t["proxy_cpu"]))))):
            ax = axes[i, j]
            ax.axhline(1.0, color="gray", lw=1, ls="--", label="reference")
            for (label, y), color in zip(lines, ("C0", "C2"), strict=True):
                ax.axhline(y, color=color, lw=0.8, ls=":", label=f"target, {label}")
            ax.set_xscale("log", base=2)
            ax.set_xlabel("shards K")
            ax.set_ylabel(what)
            ax.set_title(f"{name}, {res['machine']['nproc']} cores")
            ax.legend()
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def merge(paths: list[Path]) -> dict:
    """The saved results of runs on one machine as one result: every row tagged with its
    run (the file's stem, less what all the stems begin with), the first file's machine,
    each run's settings and model."""
    stems = [Path(p).stem for p in paths]
    cut = len(os.path.commonprefix(stems)) if len(stems) > 1 else 0
    runs = [(stem[cut:] or stem, json.loads(Path(p).read_text()))
            for stem, p in zip(stems, paths, strict=True)]
    machines = {json.dumps(r["machine"].get("cpu_model")) for _, r in runs}
    if len(machines) > 1:
        raise SystemExit(f"--merge: runs from different CPUs {sorted(machines)}")
    rows = [{**row, "run": name} for name, r in runs for row in r["rows"]]
    rows.sort(key=lambda r: (r["scene"], r["k"], r["mode"]))
    return {"machine": runs[0][1]["machine"], "targets": runs[0][1]["targets"], "rows": rows,
            "runs": {name: r["settings"] for name, r in runs},
            "model": {f"{scene}, {name}": m for name, r in runs
                      for scene, m in r.get("model", {}).items()}}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.render.bench_strong_scaling",
                                 description=__doc__)
    add_image_flags(ap)
    ap.add_argument("--spp-per-pass", type=int, default=SPP_PER_PASS)
    ap.add_argument("--modes", nargs="+", default=["exact", "proxy"])
    ap.add_argument("--ref-runs", type=int, default=1,
                    help="runs of the reference per scene: the first before the distributed "
                         "ones, the others after; ratios against their mean")
    cores = os.cpu_count() or 2
    default_ks = [k for k in (1, 2, 4, 8, 12, 14) if k <= max(2, cores - 2)]
    ap.add_argument("--ks", type=int, nargs="+", default=default_ks)
    ap.add_argument("--tag", default=None, help="results file suffix (default: <nproc>core)")
    add_byte_slack_flag(ap)
    add_output_flags(ap)
    ap.add_argument("--merge", nargs="+", type=Path, default=None,
                    help="saved results of runs on one machine: one table and plot of all "
                         "their rows (no rendering)")
    args = smoke(ap.parse_args(argv), scenes=["forest"], size="tiny", width=32, height=24,
                 spp=1, spp_per_pass=1, ks=[2], ref_runs=2)
    res = merge(args.merge) if args.merge else bench(args)
    tag = args.tag or f"{os.cpu_count()}core"
    finish(res, args.out / f"strong_scaling_{tag}.json", plot=plot, markdown=markdown,
           section=f"bench_strong_scaling_{tag}", update_readme=not args.no_readme,
           intro=(f"`python -m bench.render.bench_strong_scaling --merge "
                  f"{' '.join(p.name for p in args.merge)} --tag {tag}` (in results/; "
                  if args.merge else f"`python -m bench.render.bench_strong_scaling` on {tag} (")
           + "`{json}`):\n\n![]({png})\n\n")
    (args.out / "strong_scaling_partial.json").unlink(missing_ok=True)  # the whole run is saved


if __name__ == "__main__":
    main()
