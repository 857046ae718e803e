"""`python -m nprt.proxies.ship`: train the proxies the demo scenes need (default config and
policy) into proxies/shipped/, so rendering the demos needs no torch. Needs torch itself.
`--sizes massive` opens forest:massive as metadata (written once to the scene cache) and
trains its proxies as parallel Ray tasks (nprt.proxies.tasks) on a local Ray."""

from __future__ import annotations

import argparse
import logging
import sys
import time

from nprt.proxies.cache import SHIPPED_DIR, SUFFIX, TIMING_SUFFIX, ProxyCache, file_name
from nprt.proxies.config import DEFAULT_WIDTHS, ProxyConfig
from nprt.proxies.policy import plan_proxies

log = logging.getLogger(__name__)

SIZES = ("default", "small", "tiny")
SHARDS = 2  # with 2 or more shards every demo mesh is non-local somewhere
TARGET_ACCURACY = 0.97  # the render path's default in plan_proxies
# The test family's scene (scene/demos/family.py) at the size its slow proxy-mode test and
# `bench.proxy.bench_proxy_family` render, with every width the policy tries: the test forces
# width 16, and the benchmark's policy run (--proxy-width 0) needs the rest. No training.
FAMILY_SIZE, FAMILY_WIDTHS = "small", DEFAULT_WIDTHS
# The foliage scene (family.build_foliage) at the size bench_proxy_accuracy renders, and at
# the size tests/distributed/test_accuracy_target.py renders with width 16 and TEST_STEPS.
FOLIAGE_SIZE = "default"
TEST_SIZE, TEST_STEPS = "tiny", 3000


def _open(name: str, size: str):
    """(scene or metadata, trainer): massive scenes train as Ray tasks, never in memory."""
    from nprt.scene.demos import make_demo

    if size != "massive":
        return make_demo(name, size=size), None
    import ray

    from nprt.proxies.tasks import RayTrainer
    from nprt.scene.store import open_scene

    meta = open_scene(f"{name}:{size}")
    if not ray.is_initialized():
        ray.init(include_dashboard=False, log_to_driver=False)
    return meta, lambda out: RayTrainer(meta.source, out,
                                        names={i: m.name for i, m in enumerate(meta.meshes)})


def add_curves(cache: ProxyCache, scene, widths=DEFAULT_WIDTHS,
               config: ProxyConfig | None = None) -> int:
    """Record the held-out error curve (nprt.proxies.evaluate.error_curve, on the report's own
    held-out rays) in cached proxies of `scene` trained before it was part of the report;
    the nets are untouched. Returns how many files were rewritten."""
    from nprt.proxies.config import EVAL_SEED_OFFSET
    from nprt.proxies.evaluate import error_curve
    from nprt.proxies.inference import Proxy
    from nprt.proxies.sampling import sample_rays

    config = config or ProxyConfig()
    done = 0
    for mesh in scene.meshes:
        for w in widths:
            cfg = config.with_width(w)
            proxy = cache.get(mesh, cfg)
            if proxy is None or "curve" in proxy.meta.get("report", {}):
                continue
            samples = sample_rays(mesh, cfg.eval_samples, cfg.seed + EVAL_SEED_OFFSET, cfg.grid)
            meta = dict(proxy.meta)
            meta["report"] = {**meta["report"],
                              "curve": error_curve(proxy, samples, meta["threshold"])}
            fresh = Proxy(meta, proxy.models)
            fresh.timing = proxy.timing
            cache.put(mesh, cfg, fresh)
            done += 1
    return done


def main(argv=None) -> int:
    from nprt.scene.demos import DEMO_SIZES, DEMOS, family
    from nprt.scene.partition import partition

    ap = argparse.ArgumentParser(prog="python -m nprt.proxies.ship", description=__doc__)
    ap.add_argument("--demos", nargs="*", default=list(DEMOS))
    ap.add_argument("--sizes", nargs="*", default=list(SIZES),
                    choices=[*SIZES, "massive"])
    ap.add_argument("--out", default=str(SHIPPED_DIR))
    ap.add_argument("--steps", type=int, default=ProxyConfig.steps,
                    help="smoke runs only: a non-default step budget gives files the render "
                         "path's default config does not look up")
    ap.add_argument("--family", action=argparse.BooleanOptionalAction, default=True,
                    help=f"also the test family scene ({FAMILY_SIZE}, widths {FAMILY_WIDTHS})")
    ap.add_argument("--prune", action="store_true",
                    help="delete files in --out that no demo mesh uses any more")
    ap.add_argument("--curves-only", action="store_true",
                    help="train nothing: add the held-out error curve to cached proxies "
                         "whose report lacks it")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cache = ProxyCache(args.out, shipped_dir=None)
    config = ProxyConfig(steps=args.steps)
    keep, t0 = set(), time.perf_counter()
    jobs = [(name, size, DEFAULT_WIDTHS) for name in args.demos for size in args.sizes
            if size in DEMO_SIZES[name]]
    if args.family:
        jobs.append(("family", FAMILY_SIZE, FAMILY_WIDTHS))
        jobs.append(("foliage", FOLIAGE_SIZE, DEFAULT_WIDTHS))
        jobs.append(("foliage-test", TEST_SIZE, (16,)))
    for name, size, widths in jobs:
        if name in ("family", "foliage", "foliage-test"):
            build = family.build if name == "family" else family.build_foliage
            scene, trainer = build(size), None
        else:
            scene, trainer = _open(name, size)
        cfg = ProxyConfig(steps=TEST_STEPS) if name == "foliage-test" else config
        if args.curves_only:
            print(f"{name} {size}: {add_curves(cache, scene, widths, cfg)} curves added",
                  flush=True)
            continue
        plan = plan_proxies(scene, partition(scene, SHARDS), TARGET_ACCURACY, cache,
                            train=True, config=cfg, widths=widths,
                            progress=sys.stderr.isatty(),
                            trainer=trainer and trainer(cache.dir))
        for d in plan.decisions:
            mesh = scene.meshes[d.mesh]
            keep.update(file_name(mesh, cfg.with_width(w)) for w in d.tried)
            print(f"{name:9s} {size:7s} {d.name:10s} {d.decision:9s} w={d.width} "
                  f"acc={d.accuracy} bytes={d.proxy_bytes} {d.reason}", flush=True)
    files = sorted(cache.dir.glob(f"*{SUFFIX}"))
    if args.prune:
        for f in files:
            if f.name not in keep:
                f.unlink()
                f.with_suffix(TIMING_SUFFIX).unlink(missing_ok=True)
                print(f"pruned {f.name}")
        files = [f for f in files if f.name in keep]
    total = sum(f.stat().st_size for f in files)
    print(f"{len(files)} proxy files, {total / 1e6:.2f} MB in {cache.dir} "
          f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
