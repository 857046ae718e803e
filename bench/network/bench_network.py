"""Renders across real, shaped network links, and a trace-driven model of larger clusters:
the analogues of the paper's Table 4 (time per phase against bandwidth) and Table 2 (time
against the node count).

    python -m bench.network.bench_network bandwidth   # real: 2 shaped nodes (deploy/netcluster.sh)
    python -m bench.network.bench_network scaling     # traces with K = 2..8 shards, then the model
    python -m bench.network.bench_network report      # tables, plots and bench/README.md section

`bandwidth` brings up a 2-node cluster with deploy/netcluster.sh (needs root and network
namespaces; or joins --ray-address, a cluster that netcluster.sh made) and renders each
scene in exact and proxy mode with K = 2 shards, one per node, at every link bandwidth
(re-shaped in place, the shard pool stays warm). Every render records the coordinator's
step trace (workers/runtime/calltrace.py: every wavefront step of every shard, with its CPU
seconds and the parcels it took in and sent shard to shard), each shard process's CPU
seconds and the coordinator's. `scaling` records traces with K = 2, 3, 4, 6, 8 shards (or
`--ks`) on a local Ray (only bytes and each step's CPU seconds matter there) and replays
them with bench/network/netmodel.py on K dedicated nodes. The model is validated against
the real K = 2 renders first: see bench/network/network_report.py for every column.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make the repository importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
# netcluster.sh turns on Ray's token authentication; Ray reads this once, at import. Only
# when run as a program: an importer (a test, another bench) keeps its process's Ray auth.
if __name__ == "__main__":
    os.environ.setdefault("RAY_AUTH_MODE", "token")

import numpy as np  # noqa: E402
import ray  # noqa: E402

from bench.common import (  # noqa: E402
    RECORDED,
    RESULTS,
    add_render_flags,
    machine,
    render_settings,
    smoke,
    start_ray,
)
from bench.network.netmodel import film_bytes  # noqa: E402
from nprt.scene.demos import make_demo  # noqa: E402
from nprt.workers.render import render  # noqa: E402
from nprt.workers.runtime.coordinator import Coordinator  # noqa: E402
from nprt.workers.runtime.pool import PoolRegistry  # noqa: E402

log = logging.getLogger(__name__)

NETCLUSTER = Path(__file__).resolve().parents[2] / "deploy" / "netcluster.sh"
BANDWIDTHS = ("20gbit", "4gbit", "2gbit", "1gbit", "100mbit", "10mbit")
KS = (2, 3, 4, 6, 8)
MODES = ("exact", "proxy")
_UNITS = {"gbit": 1e9, "mbit": 1e6, "kbit": 1e3}


def bits_per_s(bw: str) -> float:
    for unit, scale in _UNITS.items():
        if bw.endswith(unit):
            return float(bw[:-len(unit)]) * scale
    raise ValueError(f"bandwidth {bw!r}: expected e.g. 1gbit or 100mbit")


def netcluster(*args: str) -> str:
    """Run deploy/netcluster.sh; returns its stdout."""
    out = subprocess.run(["bash", str(NETCLUSTER), *args], check=True, text=True,
                         capture_output=True, env={**os.environ, "PYTHON": sys.executable})
    return out.stdout.strip()


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process on this host (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def traced_render(scene, s, pools: PoolRegistry) -> dict:
    """One render on the registry's warm pool for (scene, s): wall time, statistics, shard
    info, step trace, the coordinator's CPU seconds, and each shard process's CPU seconds
    over its busy seconds (how much of its steps' time it had a core)."""
    coord = Coordinator(scene, s, pools=pools, trace=True)
    pids = [i["pid"] for i in coord.shard_info]
    cpu0 = [cpu_seconds(p) for p in pids]
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    try:
        result = render(scene, s, renderer=coord)
        wall = time.perf_counter() - t0
        cpu = [cpu_seconds(p) - c for p, c in zip(pids, cpu0, strict=True)]
    finally:
        coord.close()  # the pool goes back to the registry, warm; info() still answers
    info = coord.info()
    if info["reruns"]:  # its wall and trace include the run given up (calltrace.py)
        log.warning("%s K=%d %s: re-run %d time(s) after a lost shard", scene.name, s.shards,
                    s.mode, info["reruns"])
    busy = [sh["busy_s"] for sh in info["shard_stats"]]
    return {"wall_s": round(wall, 4), "load_average": round(load, 2),
            "stats": result.stats.to_dict(), "shard_stats": info["shard_stats"],
            "window": coord.window, "reruns": info["reruns"], "cpu_s": [round(c, 3) for c in cpu],
            "coordinator_cpu_s": info["coordinator_cpu_s"],
            "cpu_over_busy": [round(c / max(b, 1e-9), 4) for c, b in zip(cpu, busy,
                                                                             strict=True)],
            "trace": coord.trace.to_dict(), "film_bytes": film_bytes(s)}


# -- the real cluster ------------------------------------------------------------------------


@ray.remote(num_cpus=0)
def _blob(nbytes: int) -> np.ndarray:
    return np.ones(nbytes, np.uint8)


@ray.remote(num_cpus=0)
def _size(x: np.ndarray) -> int:
    return len(x)


def link_throughput(bw: str, tries: int = 2) -> float:
    """Bits per second of one Ray object moving node 0 -> node 1 (both links on its path),
    the best of `tries`; about half a second of data at the shaped rate."""
    nbytes = int(min(max(bits_per_s(bw) / 8 * 0.5, 1e6), 64e6))
    on = [{"resources": {f"netnode{i}": 0.001}} for i in (0, 1)]
    best = 0.0
    for _ in range(tries):
        small, big = _blob.options(**on[0]).remote(1), _blob.options(**on[0]).remote(nbytes)
        ray.wait([small, big], num_returns=2, fetch_local=False)
        base = np.inf  # a task's round trip without data (the first may start a worker)
        for _ in range(3):
            t0 = time.perf_counter()
            ray.get(_size.options(**on[1]).remote(small))
            base = min(base, time.perf_counter() - t0)
        t0 = time.perf_counter()
        ray.get(_size.options(**on[1]).remote(big))
        best = max(best, nbytes * 8 / max(time.perf_counter() - t0 - base, 1e-3))
    return best


def run_bandwidth(args) -> dict:
    s = render_settings(args, shards=2)
    own = args.ray_address is None
    if own:
        address = netcluster("up", "2", "--bandwidth", args.bandwidths[0])
    else:
        address = args.ray_address
    out = {"settings": s.model_dump(), "bandwidths": list(args.bandwidths), "repeat":
           args.repeat, "machine": machine(2), "links": {}, "runs": []}
    try:
        ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING)
        out["nodes"] = [n["NodeManagerAddress"] for n in ray.nodes() if n["Alive"]]
        for bw in args.bandwidths:
            netcluster("shape", "--bandwidth", bw)
            out["links"][bw] = round(link_throughput(bw))
            log.warning("link %s: Ray objects move at %.1f Mbit/s", bw, out["links"][bw] / 1e6)
        for name in args.scenes:
            scene = make_demo(name, args.size)
            for mode in MODES:
                sm = s.model_copy(update={"mode": mode})
                pools = PoolRegistry()
                try:
                    traced_render(scene, sm, pools)  # warm-up: the first render is slower
                    for bw in args.bandwidths:
                        netcluster("shape", "--bandwidth", bw)
                        runs = [traced_render(scene, sm, pools) for _ in range(args.repeat)]
                        best = min(runs, key=lambda r: r["wall_s"])
                        best.update(scene=name, mode=mode, bandwidth=bw,
                                    walls_s=[r["wall_s"] for r in runs])
                        out["runs"].append(best)
                        log.warning("%s %s %s: %.2f s (%s)", name, mode, bw, best["wall_s"],
                                    best["walls_s"])
                finally:
                    pools.close()
        out["machine"]["load_average_after"] = os.getloadavg()
    finally:
        if ray.is_initialized():
            ray.shutdown()
        if own:
            netcluster("down")
    return out


# -- traces for the model ----------------------------------------------------------------------


def run_scaling(args) -> dict:
    s = render_settings(args)
    out = {"settings": s.model_dump(), "ks": list(args.ks), "machine": machine(max(args.ks)),
           "runs": []}
    start_ray(max(args.ks))
    try:
        for name in args.scenes:
            scene = make_demo(name, args.size)
            # warm-up, not recorded: the first render of a scene in a process costs more
            # (sculpture exact K = 2, first of its scene: 2.21 shard CPU s, K = 3 1.27)
            pools = PoolRegistry()
            try:
                traced_render(scene, s.model_copy(update={"shards": min(args.ks)}), pools)
            finally:
                pools.close()
            for mode in MODES:
                for k in args.ks:
                    sk = s.model_copy(update={"mode": mode, "shards": k})
                    pools = PoolRegistry()
                    try:
                        run = traced_render(scene, sk, pools)
                    finally:
                        pools.close()
                    run.update(scene=name, mode=mode, k=k)
                    out["runs"].append(run)
                    log.warning("%s %s K=%d: %.2f s, %.1f MB", name, mode, k, run["wall_s"],
                                run["stats"]["total_bytes"] / 1e6)
        out["machine"]["load_average_after"] = os.getloadavg()
    finally:
        ray.shutdown()
    return out


def appended(old: dict, new: dict) -> dict:
    """`new` scaling runs added to `old` (same settings; a (scene, mode, K) run in both is
    taken from `new`), with the machine and load of each recording kept."""
    if old["settings"] != new["settings"]:
        raise SystemExit("--append: the recorded network_scaling.json has other settings "
                         f"({old['settings']}); re-record it instead")
    key = ("scene", "mode", "k")
    fresh = {tuple(r[x] for x in key) for r in new["runs"]}
    runs = [r for r in old["runs"] if tuple(r[x] for x in key) not in fresh] + new["runs"]
    runs.sort(key=lambda r: (r["scene"], r["mode"], r["k"]))
    scenes = list(dict.fromkeys(r["scene"] for r in new["runs"]))
    return {**old, "ks": sorted({*old["ks"], *new["ks"]}), "runs": runs,
            "recorded_ks": old.get("recorded_ks", old["ks"]),
            "appended": [*old.get("appended", []), {"ks": new["ks"], "scenes": scenes,
                                                    "machine": new["machine"]}]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("what", choices=("bandwidth", "scaling", "report"), nargs="?")
    ap.add_argument("--size", choices=("tiny", "small", "default"), default="default")
    ap.add_argument("--scenes", default="forest,sculpture")
    ap.add_argument("--bandwidths", default=",".join(BANDWIDTHS))
    ap.add_argument("--ks", default=",".join(map(str, KS)))
    ap.add_argument("--repeat", type=int, default=2, help="renders per point; the fastest kept")
    ap.add_argument("--append", action="store_true",
                    help="scaling: add these K to the recorded network_scaling.json")
    ap.add_argument("--ray-address", default=None,
                    help="a cluster made by deploy/netcluster.sh (default: bring one up)")
    add_render_flags(ap, RESULTS)
    # smoke: the scaling run (no shaped links) on a tiny scene, reported beside the
    # recorded bandwidth table
    args = smoke(ap.parse_args(argv), what="scaling", size="tiny", scenes="sculpture", ks="2",
                 width=16, spp=1, bounces=1, shadow_rays=1, repeat=1)
    if args.what is None:
        ap.error("what: choose bandwidth, scaling or report")
    args.scenes = [x for x in args.scenes.split(",") if x]
    args.bandwidths = [x for x in args.bandwidths.split(",") if x]
    args.ks = [int(x) for x in args.ks.split(",") if x]
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    from bench.network.network_report import report

    args.out.mkdir(parents=True, exist_ok=True)
    if args.smoke and not (args.out / "network_bandwidth.json").exists():
        shutil.copy(RECORDED / "network_bandwidth.json", args.out)
    if args.what != "report":
        res = run_bandwidth(args) if args.what == "bandwidth" else run_scaling(args)
        path = args.out / f"network_{args.what}.json"
        if args.append and args.what == "scaling" and path.exists():
            res = appended(json.loads(path.read_text()), res)
        path.write_text(json.dumps(res))
    return report(args.out, update_readme=not args.no_readme)


if __name__ == "__main__":
    sys.exit(main())
