"""What the machine itself charges for busy neighbours: N copies of one CPU-bound render (the
single-process reference, no Ray) start together, and each copy's process CPU is compared
with one copy's alone.

On independent cores every copy costs the same CPU at any N. Where cores share something
(hyperthreads of one physical core, turbo headroom, the last-level cache, memory bandwidth,
a hypervisor's neighbours) each copy costs more as N grows. Issue 20's CPU targets weigh a
K-shard render (K shards and a coordinator busy at once) against the reference alone, so the
figure at N = K + 1 is the machine's share of that ratio, before any of nprt's.

    python -m bench.render.bench_contention                    # city; N = 1, 2, 4, ... cores
    python -m bench.render.bench_contention --ns 1 8 9 16 --rounds 1
    python -m bench.render.bench_contention --smoke
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import queue
import statistics
import time

from bench.common import add_image_flags, add_output_flags, finish, smoke, stored_scene

SECTION = "bench_contention"


WAIT_S = 900  # a copy that neither answers nor exits within this fails the run


def _copy(scene_name: str, size: str, image: dict, barrier, out) -> None:
    """One copy: load the scene, warm the kernels on a tiny render (not timed), wait for
    the others, then render once and put (process CPU s, wall s) on out."""
    from nprt.workers.render import render
    from nprt.workers.settings import RenderSettings

    scene = stored_scene(scene_name, size).load()
    render(scene, RenderSettings(width=8, height=8, spp=1, shards=0))
    s = RenderSettings(**image, seed=0, shards=0)
    barrier.wait(timeout=WAIT_S)  # a copy that died breaks it: the others stop too
    c0, t0 = time.process_time(), time.perf_counter()
    render(scene, s)
    out.put((time.process_time() - c0, time.perf_counter() - t0))


def together(n: int, scene_name: str, size: str, image: dict) -> list[tuple[float, float]]:
    """[(CPU s, wall s)] of n copies started at once (fresh processes: spawn). Raises
    RuntimeError naming the exit codes when a copy fails."""
    ctx = mp.get_context("spawn")
    barrier, out = ctx.Barrier(n), ctx.Queue()
    procs = [ctx.Process(target=_copy, args=(scene_name, size, image, barrier, out))
             for _ in range(n)]
    for p in procs:
        p.start()
    got, deadline = [], time.monotonic() + WAIT_S
    try:
        while len(got) < n:
            try:
                got.append(out.get(timeout=1.0))
            except queue.Empty:
                failed = [p.exitcode for p in procs if p.exitcode not in (None, 0)]
                if failed or time.monotonic() > deadline:
                    raise RuntimeError(f"{n} copies of the {scene_name} reference: "
                                       f"{len(got)} answered; exit codes "
                                       f"{[p.exitcode for p in procs]}") from None
    finally:
        for p in procs:
            if len(got) < n:
                p.terminate()
            p.join()
    return got


def default_ns(cores: int) -> list[int]:
    """1, 2, 4, ... up to the core count, and the core count itself."""
    ns, n = [], 1
    while n < cores:
        ns.append(n)
        n *= 2
    return ns + [cores]


def bench(args) -> dict:
    image = {"width": args.width, "height": args.height, "spp": args.spp}
    rows = []
    for name in args.scenes:
        stored_scene(name, args.size)  # built once here, not by every copy at once
        mine = []
        for n in args.ns:
            for r in range(args.rounds):
                load = os.getloadavg()[0]
                got = together(n, name, args.size, image)
                cpu = [c for c, _ in got]
                mine.append({"scene": name, "n": n, "round": r, "cpu_s": cpu,
                             "wall_s": [w for _, w in got],
                             "median_cpu_s": statistics.median(cpu), "load_before": load})
                print(f"{name} N={n:3d} round {r}: CPU per copy {min(cpu):.2f}-{max(cpu):.2f} s"
                      f" (median {mine[-1]['median_cpu_s']:.2f}); load before {load:.1f}",
                      flush=True)
        # one copy alone: the median over every N = 1 round (one round moved 8 % here)
        ones = [c for row in mine if row["n"] == 1 for c in row["cpu_s"]]
        if ones:
            alone = statistics.median(ones)
            for row in mine:
                row["inflation"] = row["median_cpu_s"] / alone
                row["worst"] = max(row["cpu_s"]) / alone
        rows += mine
    from bench.render.bench_strong_scaling import cpu_model

    return {"cores": os.cpu_count(), "cpu_model": cpu_model(), "settings": {
        **image, "scenes": args.scenes, "size": args.size, "ns": args.ns,
        "rounds": args.rounds}, "rows": rows}


def markdown(res: dict) -> str:
    s = res["settings"]
    out = [f"Machine: {res['cores']} cores ({res['cpu_model']}); the reference at "
           f"{s['width']}x{s['height']}, {s['spp']} spp, N copies at once, "
           f"{s['rounds']} round(s) each.", "",
           "| scene | N | round | CPU s per copy (min-max) | median | x one alone (median) "
           "| x one alone (worst copy) | wall s (max) | load before |",
           "|---|---:|---:|---|---:|---:|---:|---:|---:|"]
    for r in res["rows"]:
        out.append(f"| {r['scene']} | {r['n']} | {r['round']} | {min(r['cpu_s']):.2f}-"
                   f"{max(r['cpu_s']):.2f} | {r['median_cpu_s']:.2f} | "
                   f"{r.get('inflation', float('nan')):.2f}x | {r.get('worst', float('nan')):.2f}x"
                   f" | {max(r['wall_s']):.2f} | {r['load_before']:.1f} |")
    return "\n".join(out)


def plot(res: dict, png) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for name in sorted({r["scene"] for r in res["rows"]}):
        rs = [r for r in res["rows"] if r["scene"] == name and "inflation" in r]
        if not rs:
            continue
        xs = [r["n"] for r in rs for _ in r["cpu_s"]]
        ys = [c * r["inflation"] / r["median_cpu_s"] for r in rs for c in r["cpu_s"]]
        ax.plot(xs, ys, "o", alpha=0.4, label=f"{name}: each copy")
        ns = sorted({r["n"] for r in rs})
        med = [statistics.median([r["inflation"] for r in rs if r["n"] == n]) for n in ns]
        ax.plot(ns, med, "-", label=f"{name}: median")
    ax.axhline(1.0, color="gray", ls=":", label="independent cores")
    ax.axvline(res["cores"], color="gray", ls="--", lw=0.8, label="cores")
    ax.set_xlabel("copies running at once (N)")
    ax.set_ylabel("CPU per copy / one copy alone")
    ax.set_title(f"{res['cores']} cores: {res['cpu_model'][:40]}", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.render.bench_contention",
                                 description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    add_image_flags(ap, 320, 180, 16)
    ap.set_defaults(scenes=["city"])
    ap.add_argument("--ns", type=int, nargs="+", default=default_ns(os.cpu_count() or 1),
                    help="copies at once (default: 1, 2, 4, ... and the core count)")
    ap.add_argument("--rounds", type=int, default=2)
    add_output_flags(ap)
    args = smoke(ap.parse_args(argv), scenes=["forest"], size="tiny", width=16, height=12,
                 spp=1, ns=[1, 2], rounds=1)
    if any(n < 1 for n in args.ns) or args.rounds < 1:
        ap.error("--ns and --rounds must be 1 or more")
    finish(bench(args), args.out / f"{SECTION}.json", plot=plot, markdown=markdown,
           section=SECTION, update_readme=not args.no_readme,
           intro="`python -m bench.render.bench_contention` (`{json}`):\n\n![]({png})\n\n")


if __name__ == "__main__":
    main()
