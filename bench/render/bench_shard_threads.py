"""Where a shard process's CPU goes, thread by thread, during a render: its wavefront thread
(OS name `nprt-wavefront`), the Python threads Ray runs the actor's calls on (`deliver`,
`poll`, `collect`: parcels are unpickled there), and Ray's own C++ threads, by name
(`worker.io`, `server.poll0`, ...). Read from /proc/<pid>/task (Linux) for every thread of
every shard process, from the started pool (meshes and proxies loaded) to the end of the
render, so the pool's start is not in it. `bench_strong_scaling` reports the shards' CPU
outside the wavefront thread as one figure ("Ray threads"); this splits it.

    python -m bench.render.bench_shard_threads                  # city; K = 4; both modes
    python -m bench.render.bench_shard_threads --scenes forest --k 8 --modes proxy
    python -m bench.render.bench_shard_threads --smoke
"""

from __future__ import annotations

import argparse
import os
import time
from collections import Counter

from bench.common import (
    add_image_flags,
    add_output_flags,
    finish,
    machine,
    smoke,
    stat_cpu,
    stored_scene,
)

SECTION = "bench_shard_threads"


def threads_cpu(pid: int) -> dict[tuple[int, str], float]:
    """{(tid, OS thread name): user + system CPU s so far} of every live thread of pid."""
    out = {}
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for tid in tids:
        try:
            with open(f"/proc/{pid}/task/{tid}/comm") as f:
                name = f.read().strip()
            out[(int(tid), name)] = stat_cpu(f"/proc/{pid}/task/{tid}/stat")
        except OSError:  # the thread ended between the listing and the read
            continue
    return out


def group(name: str) -> str:
    """A thread's group: the wavefront thread, a Python thread of Ray's (they keep the
    process title, `ray::...`), or Ray's C++ thread by its own name."""
    from nprt.workers.runtime.remote import WAVEFRONT_THREAD

    if name == WAVEFRONT_THREAD[:15]:
        return "wavefront"
    return "ray python threads" if name.startswith("ray::") else name


def split(before: dict, after: dict) -> Counter:
    """CPU s by group between two `threads_cpu` readings of one process (a thread born in
    between counts from zero)."""
    got = Counter()
    for key, cpu in after.items():
        got[group(key[1])] += cpu - before.get(key, 0.0)
    return got


def run(scene, s) -> dict:
    from nprt.workers.render import make_renderer, render

    coord = make_renderer(scene, s)
    try:
        pids = [int(i["pid"]) for i in coord.shard_info]
        before = {p: threads_cpu(p) for p in pids}
        t0 = time.perf_counter()
        render(scene, s, renderer=coord)
        wall = time.perf_counter() - t0
        after = {p: threads_cpu(p) for p in pids}
        info = coord.info()
    finally:
        coord.close()
    groups = Counter()
    for p in pids:
        groups.update(split(before[p], after[p]))
    parcels = sum(x["calls"] for x in info["shard_stats"])  # parcels delivered to shards
    return {"render_s": round(wall, 3), "parcels": parcels,
            "cpu_s": {k: round(v, 3) for k, v in groups.most_common()}}


def bench(args) -> dict:
    from nprt.workers.settings import RenderSettings

    rows = []
    for name in args.scenes:
        scene = stored_scene(name, args.size).load()
        for mode in args.modes:
            s = RenderSettings(width=args.width, height=args.height, spp=args.spp, seed=0,
                               shards=args.k, mode=mode)
            r = run(scene, s) | {"scene": name, "mode": mode, "k": args.k}
            total = sum(r["cpu_s"].values())
            ray = total - r["cpu_s"].get("wavefront", 0.0)
            r["total_cpu_s"] = round(total, 3)
            r["ray_ms_per_parcel"] = round(1e3 * ray / max(r["parcels"], 1), 3)
            rows.append(r)
            print(f"{name} {mode} K={args.k}: {total:.2f} CPU s in shards, wavefront "
                  f"{r['cpu_s'].get('wavefront', 0.0):.2f} s; the rest {ray:.2f} s over "
                  f"{r['parcels']} parcels ({r['ray_ms_per_parcel']:.2f} ms each)", flush=True)
    return {"machine": machine(os.cpu_count()), "settings": {
        "scenes": args.scenes, "size": args.size, "width": args.width, "height": args.height,
        "spp": args.spp, "k": args.k, "modes": args.modes}, "rows": rows}


def markdown(res: dict) -> str:
    groups = sorted({g for r in res["rows"] for g in r["cpu_s"]},
                    key=lambda g: -sum(r["cpu_s"].get(g, 0.0) for r in res["rows"]))
    shown = groups[:8]
    out = ["| scene | mode | K | render s | shards' CPU s | "
           + " | ".join(shown) + " | other | parcels | Ray's CPU per parcel, ms |",
           "|---|---|---:|---:|---:|" + "---:|" * (len(shown) + 3)]
    for r in res["rows"]:
        total = r["total_cpu_s"]
        # /proc counts whole ticks (10 ms): a tiny render can show no CPU at all
        cells = [f"{r['cpu_s'].get(g, 0.0):.2f} ({100 * r['cpu_s'].get(g, 0.0) / total:.0f} %)"
                 if total > 0 else f"{r['cpu_s'].get(g, 0.0):.2f}" for g in shown]
        other = max(0.0, total - sum(r["cpu_s"].get(g, 0.0) for g in shown))  # not -0.00
        out.append(f"| {r['scene']} | {r['mode']} | {r['k']} | {r['render_s']:.2f} | "
                   f"{total:.2f} | " + " | ".join(cells) + f" | {other:.2f} | {r['parcels']} | "
                   f"{r['ray_ms_per_parcel']:.2f} |")
    return "\n".join(out)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.render.bench_shard_threads",
                                 description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    add_image_flags(ap)
    ap.set_defaults(scenes=["city"])
    ap.add_argument("--k", type=int, default=4)
    ap.add_argument("--modes", nargs="+", default=["exact", "proxy"])
    add_output_flags(ap)
    args = smoke(ap.parse_args(argv), scenes=["forest"], size="tiny", width=16, height=12,
                 spp=1, k=2, modes=["exact"])
    if args.k < 1:
        ap.error("--k must be 1 or more")
    finish(bench(args), args.out / f"{SECTION}.json", markdown=markdown, section=SECTION,
           update_readme=not args.no_readme,
           intro="`python -m bench.render.bench_shard_threads` (`{json}`):\n\n")


if __name__ == "__main__":
    main()
