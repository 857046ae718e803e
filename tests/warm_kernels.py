"""`python -m tests.warm_kernels`: compile nprt's numba kernels once, in this one process,
into numba's on-disk cache. tests/conftest.py runs it before a parallel test run when the
cache is cold (a fresh checkout): otherwise every process that starts before some process
has cached a kernel compiles it too, all at once. One exact K = 4 test
(test_exact.py -k forest-k4, 2 cores) took 99.7 s of CPU with an empty NUMBA_CACHE_DIR, 16.1 s
after this ran (15.7 s on a warm cache); this took 56.7 s of CPU. (A pool now warms
one shard a node first on a cold cache, `pool.first_cold_per_node`; this run took 62 s
of CPU on 2026-11-27, 78 s before `nearest.near_search` was compiled on its own.)

What it runs is what a shard's own warm-up runs (Shard.warm, in process, no Ray): a
reference render, then K = 4 shards of forest:small, exact and proxy (the shipped proxies,
at an accuracy target they meet, so every shard asks proxies of others' meshes), on an
image of two tiles so that a step
holds two passes. Prints the kernel modules still cold after (none expected)."""

from __future__ import annotations

import time

from nprt.scene.demos import make_demo
from nprt.workers.jitcache import cold_kernel_modules
from nprt.workers.render import render
from nprt.workers.settings import ProxySettings, RenderSettings
from nprt.workers.wavefront.inprocess import shards_in_process

BASE = dict(spp=1, spp_per_pass=1, bounces=2)


def main() -> int:
    t0 = time.perf_counter()
    before = cold_kernel_modules()
    render(make_demo("forest", "tiny"), RenderSettings(**BASE, width=16, height=12))
    scene = make_demo("forest", "small")
    # Proxy mode at an accuracy target its tree proxies meet: at the default (0.97) the
    # plan copies the trees to every shard and no proxy would be asked (nothing compiled).
    for mode in ("exact", "proxy"):  # 160x120: the warm-up's two blocks in two tiles
        shards_in_process(scene, RenderSettings(**BASE, width=160, height=120, shards=4,
                                                mode=mode, proxy=ProxySettings(
                                                    accuracy_target=0.9)))
    print(f"warm_kernels: {len(before)} cold kernel modules compiled in "
          f"{time.perf_counter() - t0:.1f} s; still cold: {cold_kernel_modules() or 'none'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
