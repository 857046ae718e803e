"""The `nprt` command line: render, demo, scenes; serve/submit, jobs and proxy register
their own subcommands."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from pydantic import ValidationError

from nprt.proxies.config import ProxyConfig
from nprt.scene.errors import SceneError
from nprt.scene.partition import BYTE_SLACK
from nprt.service.logconfig import add_log_flags
from nprt.service.preflight import CliError
from nprt.workers.settings import SPP_PER_PASS, ProxySettings

log = logging.getLogger(__name__)
# RenderSettings fields whose flag is not "--" + the field name with dashes.
_FLAG_OF = {("proxy", "width"): "--proxy-width", ("proxy", "steps"): "--proxy-steps"}


class DefaultsFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Every option's help ends with its default, unless there is none to show (None, an
    on/off flag, or a default the help already names)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        help_ = action.help or ""
        if (action.default in (None, argparse.SUPPRESS) or action.nargs == 0
                or "%(default)" in help_ or "default:" in help_):
            return help_
        return super()._get_help_string(action)


class OneLineParser(argparse.ArgumentParser):
    """argparse, but a usage error is one line `nprt: invalid option: ...`, exit 2; --help
    shows defaults (subparsers are made with this class too, so theirs do as well)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", DefaultsFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str):
        self.exit(2, f"nprt: invalid option: {self.prog}: {message} "
                     f"(see {self.prog} --help)\n")


def _add_settings_flags(p: argparse.ArgumentParser, **defaults) -> None:
    p.add_argument("--width", type=int, default=defaults.get("width", 256),
                   help="image width, pixels")
    p.add_argument("--height", type=int, default=defaults.get("height", 256),
                   help="image height, pixels")
    p.add_argument("--spp", type=int, default=defaults.get("spp", 16), help="samples per pixel")
    p.add_argument("--bounces", type=int, default=5, help="maximum bounces B")
    p.add_argument("--shadow-rays", type=int, default=4, help="shadow rays S per hit")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--russian-roulette", action="store_true",
                   help="end low-throughput paths early (from depth 3)")
    p.add_argument("--shards", type=int, default=defaults.get("shards", 0),
                   help="K shard actors; 0 = single-process reference")
    p.add_argument("--mode", choices=["exact", "proxy", "oracle"],
                   default=defaults.get("mode", "exact"), help="traversal policy of the shards")
    p.add_argument("--tile-size", type=int, default=64, help="tile edge, pixels")
    p.add_argument("--spp-per-pass", type=int, default=defaults.get("spp_per_pass", SPP_PER_PASS),
                   help="samples per pixel that one pass renders")
    p.add_argument("--byte-slack", type=float, default=BYTE_SLACK,
                   help="a shard may hold this times the geometry bytes of the largest shard "
                        "of a bytes-only placement, to balance ray work (wider: better "
                        f"balance at K >= 8, more memory; default {BYTE_SLACK:g})")
    p.add_argument("--threshold", type=float, default=None,
                   help="proxy visibility threshold (default: each proxy's calibrated one)")
    p.add_argument("--accuracy", default=None,
                   help="what the image needs against exact: a PSNR ('40dB') or 'exact'; "
                        "nprt picks each proxy's bands to meet it (default: "
                        f"{ProxySettings().accuracy:g}dB)")
    p.add_argument("--check", action="store_true",
                   help="proxy mode: afterwards, render 1/64 of the pixels exactly and report "
                        "the measured PSNR beside the accuracy target")
    p.add_argument("--band", type=float, default=None,
                   help="hand-set proxy confidence band for secondary rays, instead of "
                        f"--accuracy (wider: more exact fallback; {ProxySettings().band:g})")
    p.add_argument("--shadow-band", type=float, default=None,
                   help="hand-set band for shadow rays, instead of --accuracy (0: shadow "
                        f"rays never move; {ProxySettings().shadow_band:g})")
    p.add_argument("--proxy-width", type=int, default=None, choices=(16, 32, 64, 128, 256),
                   help="one proxy width for every mesh (default: narrowest meeting 97%%)")
    p.add_argument("--proxy-steps", type=int, default=ProxyConfig.steps,
                   help="training budget per proxy, optimiser steps (shipped proxies: the "
                        "default)")
    p.add_argument("--ray-address", default=None,
                   help="join this Ray cluster (default: start a local Ray)")
    p.add_argument("--size", default="default", choices=["default", "small", "tiny", "massive"],
                   help="size of a demo scene")


def settings_from_args(a: argparse.Namespace):
    from nprt.workers.settings import RenderSettings

    return RenderSettings(
        width=a.width, height=a.height, spp=a.spp, bounces=a.bounces,
        shadow_rays=a.shadow_rays, seed=a.seed, russian_roulette=a.russian_roulette,
        shards=a.shards, mode=a.mode, tile_size=a.tile_size,
        spp_per_pass=a.spp_per_pass,  # above --spp it is --spp (RenderSettings)
        byte_slack=a.byte_slack,
        proxy=ProxySettings(threshold=a.threshold, width=a.proxy_width, steps=a.proxy_steps,
                            check=a.check, **{k: v for k, v in (
                                ("accuracy", a.accuracy), ("band", a.band),
                                ("shadow_band", a.shadow_band)) if v is not None}))


def render_with_progress(scene, settings, ray_address=None, label="render"):
    from tqdm import tqdm

    from nprt.workers.render import render

    bar = tqdm(total=settings.width * settings.height * settings.spp, unit="path",
               unit_scale=True, desc=label, file=sys.stderr)

    def on_pass(done):
        bar.update(done.pass_.n_paths)

    try:
        return render(scene, settings, on_pass=on_pass, ray_address=ray_address)
    finally:
        bar.close()


def option_error(err: ValidationError) -> str:
    """One line naming the flag, its value and why: '--spp 0: Input should be ...'."""
    errors = err.errors()
    first = errors[0]
    loc = tuple(str(p) for p in first["loc"])
    if err.title == "ProxySettings":  # built on its own in settings_from_args
        loc = ("proxy", *loc)
    if loc:
        flag = _FLAG_OF.get(loc, "--" + loc[-1].replace("_", "-"))
        where = f"{flag} {first['input']}"
    else:
        where = "settings"
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    return f"{where}: {first['msg'].removeprefix('Value error, ')}{more}"


def preflight(settings, ray_address: str | None, uses_ray: bool) -> None:
    """Refuse before any work what would fail after it: a render that cannot fit in
    memory, a Ray cluster nobody answers at."""
    from nprt.service.preflight import check_memory

    check_memory(settings)
    if uses_ray:  # gRPC (and Ray) only in processes that will use them
        from nprt.service.ray_reach import check_ray_reachable

        check_ray_reachable(ray_address)


def cmd_render(a: argparse.Namespace) -> int:
    from nprt.scene.io import load_any
    from nprt.scene.store import open_scene
    from nprt.service.preflight import check_writable

    settings = settings_from_args(a)
    check_writable(a.output, "-o", image=True)
    if a.stats:
        check_writable(a.stats, "--stats")
    preflight(settings, a.ray_address, uses_ray=settings.shards > 0)
    # Distributed: metadata only here, each shard loads its own meshes (nprt.scene.store).
    scene = (open_scene if settings.shards > 0 else load_any)(a.scene, size=a.size)
    if a.frames is not None:
        return _render_frames(a, scene, settings)
    res = render_with_progress(scene, settings, a.ray_address)
    out = res.film.save(a.output)
    print(f"wrote {out} ({settings.width}x{settings.height}, {settings.spp} spp) "
          f"in {res.info['wall_s']:.2f} s")
    if "accuracy" in res.info:
        from nprt.proxies.check import summary_lines

        for line in summary_lines(res.info["accuracy"]):
            print(line)
    if a.stats:
        Path(a.stats).parent.mkdir(parents=True, exist_ok=True)  # as the image's is
        Path(a.stats).write_text(json.dumps(res.stats_dict(), indent=2))
        print(f"wrote {a.stats}")
    return 0


def _render_frames(a: argparse.Namespace, scene, settings) -> int:
    """--frames A:B: one image per frame, named by frame_path(-o, f), on one renderer."""
    from tqdm import tqdm

    from nprt.scene.animation import frame_range
    from nprt.workers.frames import frame_path, render_frames

    frames = frame_range(a.frames, scene.frames)
    bar = tqdm(total=settings.width * settings.height * settings.spp * len(frames),
               unit="path", unit_scale=True, desc="frames", file=sys.stderr)
    stats = []
    try:
        for done in render_frames(scene, settings, frames, ray_address=a.ray_address,
                                  on_pass=lambda f, d: bar.update(d.pass_.n_paths)):
            out = done.result.film.save(frame_path(a.output, done.frame))
            tqdm.write(f"frame {done.frame}: wrote {out} in {done.wall_s:.2f} s",
                       file=sys.stdout)
            stats.append({"frame": done.frame, "frame_wall_s": round(done.wall_s, 4),
                          **done.result.stats_dict()})
    finally:
        bar.close()
    if a.stats:
        Path(a.stats).parent.mkdir(parents=True, exist_ok=True)
        Path(a.stats).write_text(json.dumps({"frames": stats}, indent=2))
        print(f"wrote {a.stats}")
    return 0


def cmd_scenes(a: argparse.Namespace) -> int:
    from nprt.scene.demos import DEMO_SIZES, DEMOS, make_demo
    from nprt.scene.store import open_scene, prune_demos, scene_cache_dir

    if a.prune:
        gone = prune_demos()
        for d, nbytes in gone:
            print(f"deleted {d} ({nbytes / 1e6:,.1f} MB)")
        print(f"{len(gone)} stale demos deleted from {scene_cache_dir()}, "
              f"{sum(b for _, b in gone) / 1e9:.2f} GB freed")
        return 0

    cols = ("base_meshes", "instances", "instanced_triangles", "mesh_bytes", "frames")
    print(f"| demo | size | {' | '.join(cols)} |")
    print("|" + "---|" * (len(cols) + 2))
    for name in DEMOS:
        for size in a.sizes:
            if size not in DEMO_SIZES[name]:
                continue
            # massive: written once to the scene cache, summarised from its metadata
            s = (open_scene(f"{name}:{size}") if size == "massive"
                 else make_demo(name, size)).summary()
            print(f"| {name} | {size} | " + " | ".join(f"{s[c]:,}" for c in cols) + " |")
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = OneLineParser(prog="nprt", description=__doc__)
    ap.add_argument("--version", action="version", version=f"%(prog)s {nprt_version()}")
    ap.add_argument("-v", "--verbose", action="store_true",
                    help="log at INFO and print tracebacks of internal errors")
    add_log_flags(ap, global_=True)
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("render", help="render a scene file or a demo scene")
    p.add_argument("scene", help="demo name (forest, city, sculpture[:size]) or .json/.glb path")
    p.add_argument("-o", "--output", default="out.png", help=".png (sRGB) or .exr (linear)")
    p.add_argument("--stats", default=None, help="write the render statistics as JSON here")
    p.add_argument("--frames", default=None, metavar="A:B",
                   help="render frames A to B (inclusive) of an animated scene, each to "
                        "its own image: -o out_####.png (#### = the zero-padded frame)")
    _add_settings_flags(p)
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("demo", help="render a demo scene through the distributed path")
    p.add_argument("--scene", default="forest", help="demo scene name")
    p.add_argument("--out", default="out/demo", help="folder for images and statistics")
    p.add_argument("--modes", nargs="+", default=["exact", "proxy"],
                   choices=["exact", "proxy", "oracle"],
                   help="distributed modes to render next to the single-process reference")
    _add_settings_flags(p, width=192, height=144, spp=8, shards=4, spp_per_pass=8)
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("scenes", help="list the demo scenes and their statistics")
    p.add_argument("--sizes", nargs="+", default=["default"],
                   choices=["default", "small", "tiny", "massive"],
                   help="demo sizes to list (massive is generated once into "
                        "$NPRT_SCENE_CACHE, over 1 GiB)")
    p.add_argument("--prune", action="store_true",
                   help="delete the demos that older versions of nprt wrote to "
                        "$NPRT_SCENE_CACHE (this version never reads them), then exit")
    p.set_defaults(func=cmd_scenes)

    from nprt.proxies.cli import add_proxy_parsers
    from nprt.service.cli_jobs import add_jobs_parser
    from nprt.service.cli_serve import add_serve_parsers

    add_serve_parsers(sub)
    add_jobs_parser(sub)
    add_proxy_parsers(sub)
    return ap


def nprt_version() -> str:
    """The installed distribution's version; a source checkout that is not installed says
    so rather than guess."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("nprt")
    except PackageNotFoundError:
        return "(not installed)"


def log_level(args: argparse.Namespace) -> str:
    if args.log_level:
        return args.log_level
    return "INFO" if args.verbose or args.command in ("serve", "scheduler") else "WARNING"


def _cmd_demo(a):
    from nprt.service.demo import cmd_demo
    from nprt.service.preflight import check_directory

    check_directory(a.out, "--out")
    preflight(settings_from_args(a), a.ray_address, uses_ray=True)
    return cmd_demo(a)


def main(argv: list[str] | None = None) -> int:
    from nprt.service.logconfig import configure_logging

    args = build_parser().parse_args(argv)
    configure_logging(log_level(args), args.log_json)
    try:
        return int(args.func(args) or 0)
    except CliError as e:
        return _fail(str(e), 2)
    except SceneError as e:
        return _fail(f"scene error: {e}", 2)
    except ValidationError as e:
        return _fail(f"invalid option: {option_error(e)}", 2)
    except ValueError as e:
        return _fail(f"invalid input: {_first_line(e)}", 2)
    except KeyboardInterrupt:
        return _fail("interrupted", 130)
    except MemoryError:
        return _fail("out of memory: try a smaller --width/--height or --tile-size", 1)
    except OSError as e:  # e.g. the disk filled while saving
        where = e.filename if e.filename is not None else type(e).__name__
        return _fail(f"system error: {where}: {e.strerror or e}", 1)
    except Exception as e:  # a bug: one line, the traceback with -v
        if args.verbose:
            log.exception("unexpected error")
        return _fail(f"internal error: {type(e).__name__}: {_first_line(e)} (run with -v "
                     f"for the traceback)", 1)


def _fail(line: str, code: int) -> int:
    print(f"nprt: {line}", file=sys.stderr)
    return code


def _first_line(e: BaseException) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


if __name__ == "__main__":
    sys.exit(main())
