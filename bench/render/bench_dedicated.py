"""The render wall on K dedicated cores, simulated (bench/render/vtime.py): K in-process
Shards stepped in virtual time, each step lasting its own process CPU plus Ray's CPU for its
parcels (measured at the start of the run), rays regrouped into steps as they would arrive
on K cores, each shard holding for more rays as the runtime does (`remote.HOLD_RAYS`,
`HOLD_S`; `--hold 0:0` for none) and small parcels waiting in its outbox for company
(`remote.SEND_RAYS`, `SEND_S`; `--send 0:0` for none; before 2026-11-27 the model sent
every parcel at once). Each K runs twice: parcels only at a step's end, and
also during a long step (`remote.EMIT_RAYS`); `--carries 0 1048576` runs each also without
carrying what a step has left into the shard's next step (`Shard.step`, carry; the number is
`remote.CARRY_RAYS`, 0: never). What it answers
on a machine with few cores: how the wall falls with K, and what sending during a step
does where no core waits for another's CPU.

Per row: the simulated wall against the one-shard run's (its CPU on one core: the
reference's wavefront), each shard's busy share, steps, parcels (and how many left during
a step), and whether the film equals the one-shard film bit for bit (exact mode).

    python -m bench.render.bench_dedicated                       # forest, city; K 1 2 4 8
    python -m bench.render.bench_dedicated --scenes windy --ks 1 8 --modes proxy
    python -m bench.render.bench_dedicated --smoke
"""

from __future__ import annotations

import argparse
import os

import numpy as np

from bench.common import (
    add_byte_slack_flag,
    add_image_flags,
    add_output_flags,
    finish,
    machine,
    placeable_ks,
    smoke,
    stored_scene,
)
from bench.render.bench_step_hold import parse_hold
from bench.render.bench_strong_scaling import FALLBACK_RPC_S, MODEL_LINK_BPS
from bench.render.raycalls import parcel_cost
from bench.render.vtime import simulate
from nprt.scene.partition import BYTE_SLACK
from nprt.workers.runtime import remote
from nprt.workers.settings import SPP_PER_PASS, RenderSettings
from nprt.workers.wavefront.inprocess import shards_in_process


def bench(args) -> dict:
    cost = parcel_cost(calls=20 if args.smoke else 300, repeats=1 if args.smoke else 3)
    rows = []
    for name in args.scenes:
        scene = stored_scene(name, args.size).load()
        for mode in args.modes:
            one = None
            for k in placeable_ks(args.ks, scene, name):
                s = RenderSettings(width=args.width, height=args.height, spp=args.spp, seed=0,
                                   spp_per_pass=args.spp_per_pass, shards=k, mode=mode,
                                   byte_slack=args.byte_slack)
                shards = shards_in_process(scene, s)
                runs = [(e, c) for e in ([0] if k == 1 else args.emits)
                        for c in ([remote.CARRY_RAYS] if k == 1 else args.carries)]
                for emit, carry in runs:
                    r = simulate(shards, s, cost, FALLBACK_RPC_S, MODEL_LINK_BPS, emit,
                                 args.hold, args.send, carry)
                    one = r if k == 1 else one
                    row = {"scene": name, "mode": mode, "k": k, "emit_rays": emit,
                           "carry_rays": carry,
                           "wall_s": round(r["wall_s"], 3),
                           "busy": [round(float(b / r["wall_s"]), 3) for b in r["busy_s"]],
                           "steps": r["steps"], "parcels": r["parcels"],
                           "early_parcels": r["early_parcels"]}
                    if one is not None:
                        row["vs_one_shard"] = round(r["wall_s"] / one["wall_s"], 3)
                        if mode == "exact":
                            row["same_film_as_one_shard"] = bool(
                                np.array_equal(r["film"], one["film"]))
                    rows.append(row)
                    print(_line(row), flush=True)
    return {"machine": machine(os.cpu_count()), "settings": vars(args) | {"out": str(args.out)},
            "ray_parcel_cost": cost, "rpc_s": FALLBACK_RPC_S, "link_bps": MODEL_LINK_BPS,
            "rows": rows}


def _line(r: dict) -> str:
    return (f"{r['scene']} {r['mode']:6s} K={r['k']:2d} emit {r['emit_rays']:5d} carry "
            f"{_carry(r)}: wall "
            f"{r['wall_s']:7.3f} s = x{r.get('vs_one_shard', 1.0):.3f} of one shard, busy "
            f"{np.mean(r['busy']):.2f}, steps {r['steps']}, parcels {r['parcels']} "
            f"({r['early_parcels']} during a step)")


def _carry(r: dict) -> str:
    """A row's carry setting: CARRY_RAYS, or off (0, or a run from before it existed)."""
    rays = r.get("carry_rays", 0)
    return f"{rays:,}" if rays else "off"


def markdown(res: dict) -> str:
    c = res["ray_parcel_cost"]
    out = [f"Ray per parcel (this run): send {1e3 * c['send_s']:.2f} ms + "
           f"{1e9 * c['send_s_per_byte']:.2f} ms/MB, receive {1e3 * c['receive_s']:.2f} ms + "
           f"{1e9 * c['receive_s_per_byte']:.2f} ms/MB; latency {1e3 * res['rpc_s']:.1f} ms, "
           f"links {res['link_bps'] / 1e9:g} Gbit/s; hold {_hold(res)}; outbox "
           f"{_hold(res, 'send', 'none (sent at once)')}; shard bytes capped at "
           f"{res['settings'].get('byte_slack', BYTE_SLACK):g}x the bytes-only rule's "
           "largest shard. *wall* is simulated on K dedicated cores; *vs 1 shard* divides it "
           "by the one-shard wall (its CPU).",
           "",
           "| scene | mode | K | emit rays | carry | wall s | vs 1 shard | busy (mean, min) | "
           "steps | parcels | of which during a step | same film |",
           "|---|---|---:|---:|---|---:|---:|---|---:|---:|---:|---|"]
    for r in res["rows"]:
        same = r.get("same_film_as_one_shard")
        out.append(f"| {r['scene']} | {r['mode']} | {r['k']} | {r['emit_rays']} | "
                   f"{_carry(r)} | "
                   f"{r['wall_s']:.2f} | {r.get('vs_one_shard', 1.0):.3f}x | "
                   f"{np.mean(r['busy']):.2f}, {min(r['busy']):.2f} | {r['steps']} | "
                   f"{r['parcels']} | {r['early_parcels']} | "
                   f"{'' if same is None else ('yes' if same else 'NO')} |")
    return "\n".join(out) + "\n"


def plot(res: dict, png) -> None:
    """Wall on K dedicated cores against one shard's, per scene: exact and proxy, parcels at
    a step's end (dashed) and during it (solid), with the issue's K = 8 targets."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(r["scene"] for r in res["rows"]))
    fig, axes = plt.subplots(1, len(scenes), figsize=(5 * len(scenes), 4), squeeze=False)
    for ax, name in zip(axes[0], scenes, strict=True):
        rows = [r for r in res["rows"] if r["scene"] == name and "vs_one_shard" in r]
        for mode, marker in (("exact", "o"), ("proxy", "s")):
            carries = sorted({r.get("carry_rays", 0) for r in rows if r["k"] > 1})
            for emit in sorted({r["emit_rays"] for r in rows if r["k"] > 1}):
                for carry in carries:
                    rs = [r for r in rows if r["mode"] == mode and (r["k"] == 1 or (
                        r["emit_rays"] == emit and r.get("carry_rays", 0) == carry))]
                    if len(rs) > 1:
                        label = f"{mode}, {'sends during a step' if emit else 'end only'}"
                        if len(carries) > 1:
                            label += f", carry {carry:,}" if carry else ", no carry"
                        ax.plot([r["k"] for r in rs], [r["vs_one_shard"] for r in rs],
                                marker + ("-" if emit else "--"), alpha=1.0 if carry else 0.5,
                                label=label)
        ax.axhline(0.5, color="gray", lw=1, ls=":", label="exact target at K = 8")
        ax.axhline(0.3, color="black", lw=1, ls=":", label="proxy target at K = 8")
        ax.set_xscale("log", base=2)
        ax.set_xlabel("shards K, a core each (simulated)")
        ax.set_ylabel("render wall / one shard's")
        ax.set_title(name)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def _hold(res: dict, key: str = "hold", none: str = "none") -> str:
    """A (rays, seconds) setting of the run as text (a run recorded before it: none)."""
    rays, seconds = res["settings"].get(key, (0, 0.0))
    return f"{rays} rays / {seconds * 1e3:g} ms" if seconds > 0 and rays > 0 else none


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.render.bench_dedicated",
                                 description=__doc__.splitlines()[0])
    add_image_flags(ap)
    ap.add_argument("--spp-per-pass", type=int, default=SPP_PER_PASS)
    ap.add_argument("--modes", nargs="+", default=["exact", "proxy"])
    ap.add_argument("--ks", type=int, nargs="+", default=[1, 2, 4, 8],
                    help="shard counts; the first should be 1 (the baseline)")
    ap.add_argument("--hold", type=parse_hold, default=(remote.HOLD_RAYS, remote.HOLD_S),
                    help="RAYS:MS a shard holds for more rays (default: the runtime's, "
                         f"{remote.HOLD_RAYS}:{remote.HOLD_S * 1e3:g}; 0:0 for none)")
    ap.add_argument("--send", type=parse_hold, default=(remote.SEND_RAYS, remote.SEND_S),
                    help="RAYS:MS a small parcel waits in the shard's outbox for company "
                         f"(default: the runtime's, {remote.SEND_RAYS}:"
                         f"{remote.SEND_S * 1e3:g}; 0:0 for none)")
    ap.add_argument("--emits", type=int, nargs="+", default=[0, remote.EMIT_RAYS],
                    help="EMIT_RAYS settings to compare at each K > 1 (0: at a step's end)")
    ap.add_argument("--carries", nargs="+", type=int, default=[remote.CARRY_RAYS],
                    help="CARRY_RAYS settings to compare at each K > 1: what a step has left "
                         "goes on in the next step once parcels wait, if fewer (0: never; "
                         f"default: the runtime's, {remote.CARRY_RAYS})")
    add_byte_slack_flag(ap)
    add_output_flags(ap)
    args = smoke(ap.parse_args(argv), scenes=["forest"], size="tiny", width=32, height=24,
                 spp=2, modes=["exact"], ks=[1, 2], emits=[0, 1])
    if args.ks[0] != 1:
        raise SystemExit("--ks must start with 1: every wall is compared with one shard's")
    res = bench(args)
    finish(res, args.out / "bench_dedicated.json", plot=plot, markdown=markdown,
           update_readme=False)


if __name__ == "__main__":
    main()
