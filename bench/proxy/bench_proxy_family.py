"""Proxy mode on the test family's overlapping-instances scene (scene/demos/family.py) against
exact at the same seed and K: PSNR, SSIM, FLIP, ray bytes, and the internal-case counters
(secondary rays routed by a box they start inside, and how many of those missed).

    python -m bench.proxy.bench_proxy_family [--size small] [--shards 4] [--internal exact|trust]
        [--internal-margin M]

--internal trust routes rays by the nearest confident prediction even where a box they start
inside may hide a nearer surface (the paper's rule); exact (the default) sends those to
exact forwarding. --internal-margin M (0: the paper's rule) sets the unsure zone of an
internal answer around the ray's origin, in the proxy's p90 depth errors. Writes
results/proxy_family_<size>_<internal>[_w<width>][_m<M>].json.
"""

from __future__ import annotations

import argparse
import json
import os

from bench.common import RESULTS, smoke, start_ray

COUNTERS = ("proxy_targeted", "proxy_internal_targeted", "proxy_internal_ambiguous",
            "proxy_mispredictions", "proxy_internal_mispredictions", "proxy_uncertain",
            "proxy_settled")


def main(argv=None) -> int:
    import ray

    from bench.common import quality, timed_render
    from nprt.scene.demos import family
    from nprt.workers.settings import ProxySettings, RenderSettings

    ap = argparse.ArgumentParser(prog="python -m bench.proxy.bench_proxy_family")
    ap.add_argument("--size", default="small")
    ap.add_argument("--shards", type=int, default=4)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--proxy-width", type=int, default=16, choices=(0, 16, 32, 64, 128, 256),
                    help="one width for every mesh (16: the shipped ones); 0: the policy's "
                         "narrowest of 16/32/64 reaching the accuracy target (trains the "
                         "missing widths into the user cache, minutes)")
    ap.add_argument("--internal", choices=("exact", "trust"), default="exact")
    ap.add_argument("--internal-margin", type=float, default=None,
                    help="unsure zone of internal answers around the origin, in p90 depth "
                         "errors (default: ProxySettings.internal_margin)")
    ap.add_argument("--band", type=float, default=ProxySettings().band,
                    help="confidence band of secondary rays (default: the render default)")
    ap.add_argument("--shadow-band", type=float, default=ProxySettings().shadow_band,
                    help="confidence band of shadow rays (default: the render default)")
    ap.add_argument("--smoke", action="store_true", help="tiny scene, for the CI smoke test")
    # smoke: "small", whose width-16 proxies are shipped (tiny ones would be trained)
    args = smoke(ap.parse_args(argv), size="small", shards=2, width=16, spp=1)
    scene = family.build(args.size)
    base = RenderSettings(width=args.width, height=args.width * 3 // 4, spp=args.spp,
                          spp_per_pass=args.spp, bounces=5, seed=0, shards=args.shards)
    start_ray(args.shards)
    try:
        ex_row, ex_img, _ = timed_render(scene, base)
        margin = {} if args.internal_margin is None else {
            "internal_margin": args.internal_margin}
        knobs = ProxySettings(width=args.proxy_width or None, band=args.band,
                              shadow_band=args.shadow_band, internal_ambiguous=args.internal,
                              **margin)
        s = base.model_copy(update={"mode": "proxy", "proxy": knobs})
        px_row, px_img, info = timed_render(scene, s)
    finally:
        ray.shutdown()
    c = px_row["counters"]
    out = {"size": args.size, "internal": args.internal, "settings": s.model_dump(),
           "load": os.getloadavg(),
           "overlap_fraction": family.overlap_fraction(scene),
           "quality_vs_exact": quality(ex_img, px_img),
           "bytes_exact": ex_row["total_bytes"], "bytes_proxy": px_row["total_bytes"],
           "counters": {k: c.get(k, 0) for k in COUNTERS},
           "plan": info["proxy_plan"]["counts"],
           "proxies": [{k: d[k] for k in ("name", "decision", "width", "accuracy")}
                       for d in info["proxy_plan"]["decisions"]]}
    RESULTS.mkdir(exist_ok=True)
    width = "" if args.proxy_width == 16 else f"_w{args.proxy_width or 'policy'}"
    margin = "" if args.internal_margin is None else f"_m{args.internal_margin:g}"
    path = RESULTS / f"proxy_family_{args.size}_{args.internal}{width}{margin}.json"
    path.write_text(json.dumps(out, indent=1))
    print(json.dumps({k: v for k, v in out.items() if k != "settings"}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
