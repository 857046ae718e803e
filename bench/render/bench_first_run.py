"""`python -m bench.render.bench_first_run`: what a first run on a fresh install pays to
compile nprt's numba kernels. Each case runs in a fresh process with an empty numba cache
(NUMBA_CACHE_DIR, inherited by the shards of the local Ray it starts), so nothing from an
earlier run is loaded:

- reference: a 16x12 reference render of forest:tiny (the kernels the reference runs), its
  wall and process CPU;
- pool: the start of a K-shard pool of forest:small (exact) on a local Ray of K CPUs, its
  `prepare_s` (placement, shard start, load and warm-up: a pool on a cold cache warms one
  shard a node first, `nprt.workers.runtime.pool.first_cold_per_node`); then the same on
  the now warm cache.

    python -m bench.render.bench_first_run              # K = 4
    python -m bench.render.bench_first_run --smoke      # K = 1, on the caller's cache
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from bench.common import RESULTS, add_output_flags, child_env, finish, machine, smoke

ROOT = Path(__file__).resolve().parents[2]

_REFERENCE = """
import json, resource, time
from nprt.scene.demos import make_demo
from nprt.workers.render import render
from nprt.workers.settings import RenderSettings
scene = make_demo("forest", "tiny")
r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
render(scene, RenderSettings(spp=1, spp_per_pass=1, bounces=2, width=16, height=12))
r1 = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"wall_s": time.perf_counter() - t0,
                  "cpu_s": r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime}))
"""

_POOL = """
import json, logging, sys
import ray
from nprt.scene.demos import make_demo
from nprt.workers.render import render
from nprt.workers.settings import RenderSettings
k, address = int(sys.argv[1]), sys.argv[2]
ray.init(address=address, num_cpus=k if address == "local" else None, include_dashboard=False,
         log_to_driver=False, logging_level=logging.WARNING)
scene, out = make_demo("forest", "small"), {}
for run in ("cold", "warm"):
    s = RenderSettings(width=48, height=32, spp=2, spp_per_pass=2, bounces=3, shards=k)
    out[run] = render(scene, s).info["prepare_s"]
print(json.dumps(out))
"""


def _run(code: str, cache: str | None, *argv: str) -> dict:
    """code run by a fresh interpreter (NUMBA_CACHE_DIR=cache when given); its last line."""
    env = child_env(**({} if cache is None else {"NUMBA_CACHE_DIR": cache}))
    done = subprocess.run([sys.executable, "-c", code, *argv], env=env, cwd=ROOT,
                          capture_output=True, text=True, timeout=1800)
    if done.returncode != 0:
        raise RuntimeError(f"first-run case failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def bench(args) -> dict:
    res = {"machine": machine(os.cpu_count()), "k": args.k, "cold_cache": not args.smoke}
    with tempfile.TemporaryDirectory(prefix="nprt-numba-") as a, \
            tempfile.TemporaryDirectory(prefix="nprt-numba-") as b:
        # --smoke: the caller's cache (a cold one would compile for a minute)
        res["reference"] = _run(_REFERENCE, None if args.smoke else a)
        print(f"reference render: {res['reference']}", flush=True)
        # A Ray of its own, whose shards inherit the empty cache; --smoke joins the running
        # one that RAY_ADDRESS names, if any (the smoke test's).
        address = (os.environ.get("RAY_ADDRESS") or "local") if args.smoke else "local"
        res["pool"] = _run(_POOL, None if args.smoke else b, str(args.k), address)
        print(f"K = {args.k} pool start: {res['pool']}", flush=True)
    return res


def markdown(res: dict) -> str:
    cache = "an empty numba cache" if res["cold_cache"] else "the caller's numba cache"
    ref, pool = res["reference"], res["pool"]
    return (f"On {cache} ({res['machine'].get('cpus', '?')} CPUs): a 16x12 reference render "
            f"of forest:tiny took {ref['wall_s']:.1f} s ({ref['cpu_s']:.1f} s of CPU); a "
            f"K = {res['k']} exact pool of forest:small started in {pool['cold']:.1f} s, and "
            f"in {pool['warm']:.1f} s on the cache that run left.\n")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.render.bench_first_run",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--k", type=int, default=4, help="shards of the pool")
    add_output_flags(ap, RESULTS)
    args = smoke(ap.parse_args(argv), k=1)
    finish(bench(args), args.out / "bench_first_run.json", markdown=markdown,
           update_readme=False)


if __name__ == "__main__":
    main()
