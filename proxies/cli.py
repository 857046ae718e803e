"""`nprt proxy ...`: train proxies for a mesh file or every base mesh of a scene, and print
their held-out accuracy report."""

from __future__ import annotations

import argparse
import sys

from nprt.proxies.config import DEFAULT_WIDTHS, ProxyConfig, estimate_proxy_bytes

COLUMNS = ("mesh", "tris", "width", "accuracy", "FP", "FN", "depth err", "internal acc",
           "bytes", "train s", "queries/s")


def add_proxy_parsers(subparsers) -> None:
    """Register `proxy train` on an argparse subparsers object (service/cli.py's)."""
    p = subparsers.add_parser("proxy", help="neural proxies: train and report accuracy")
    sub = p.add_subparsers(dest="proxy_command", required=True)
    t = sub.add_parser("train", help="train (or fetch cached) proxies and print their accuracy")
    t.add_argument("source", metavar="MESH_OR_SCENE",
                   help="mesh file (OBJ/PLY/GLB...), scene file, or demo name (forest, city:small)")
    t.add_argument("--width", default="auto",
                   help=f"hidden width N, or 'auto': narrowest of {DEFAULT_WIDTHS} "
                        "meeting --target")
    t.add_argument("--target", type=float, default=0.97, help="held-out accuracy for 'auto'")
    t.add_argument("--steps", type=int, default=ProxyConfig.steps,
                   help="optimiser steps per proxy (both nets); with --samples and --seed it "
                        "fixes the proxy bit for bit")
    t.add_argument("--samples", type=int, default=ProxyConfig.n_samples,
                   help="training rays traced per mesh")
    t.add_argument("--out", default=None, help="cache directory (default ~/.cache/nprt/proxies)")
    t.add_argument("--seed", type=int, default=0, help="random seed of the training rays")
    t.add_argument("--size", default="default", help="demo size: default, small or tiny")
    t.add_argument("--force", action="store_true", help="retrain even when cached")
    t.set_defaults(func=run)


def _row(mesh, proxy) -> list[str]:
    from nprt.proxies.evaluate import throughput

    r, t = proxy.meta["report"], proxy.timing
    train = f"{t['train_s']:.1f}" if "train_s" in t else "?"
    return [mesh.name, str(len(mesh.faces)), str(proxy.meta["width"]), f"{r['accuracy']:.4f}",
            f"{r['fp_rate']:.4f}", f"{r['fn_rate']:.4f}", f"{100 * r['depth_err_rel']:.2f}%",
            f"{r['internal_occlusion_accuracy']:.4f}", str(proxy.nbytes),
            train + (" (capped)" if r.get("capped") else ""),
            f"{throughput(proxy) / 1e6:.2f}M"]


def markdown_table(rows: list[list[str]], columns=COLUMNS) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


def _proxy_for(mesh, config, args, cache):
    from nprt.proxies.policy import narrowest_proxy

    if args.width != "auto":
        if args.force:
            from nprt.proxies.cache import _load_trainer

            proxy = _load_trainer()(mesh, config, progress=True)
            cache.put(mesh, config, proxy)
            return proxy
        return cache.get_or_train(mesh, config, progress=True)
    if args.force:
        raise SystemExit("--force needs an explicit --width")
    proxy, _, why = narrowest_proxy(mesh, config, DEFAULT_WIDTHS, args.target, cache, True, True)
    if proxy is None:
        raise SystemExit(f"{mesh.name}: {why}")
    return proxy


def run(args: argparse.Namespace) -> int:
    from nprt.proxies.cache import ProxyCache, ProxyUnavailable
    from nprt.scene.io import load_any

    width = ProxyConfig.width if args.width == "auto" else int(args.width)
    config = ProxyConfig(width=width, steps=args.steps, n_samples=args.samples, seed=args.seed)
    scene = load_any(args.source, size=args.size, seed=args.seed)
    cache = ProxyCache(args.out)
    rows, seen = [], set()
    lightest = estimate_proxy_bytes(config.with_width(min(DEFAULT_WIDTHS)))
    for mesh in scene.meshes:
        if mesh.content_hash in seen:
            continue
        seen.add(mesh.content_hash)
        if mesh.nbytes < lightest and not args.force:
            print(f"{mesh.name}: skipped, {mesh.nbytes} B of triangles is less than a proxy "
                  f"(~{lightest} B): the policy replicates it (--force to train anyway)")
            continue
        try:
            rows.append(_row(mesh, _proxy_for(mesh, config, args, cache)))
        except ProxyUnavailable as e:
            print(f"{mesh.name}: {e}", file=sys.stderr)
            return 2
    print(markdown_table(rows))
    print(f"\ncache: {cache.dir}")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="nprt")
    add_proxy_parsers(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    raise SystemExit(main())
