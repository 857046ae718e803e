"""`nprt serve` (API workers for REST, a gRPC child process, and a scheduler child process
that renders), `nprt grpc` and `nprt scheduler` (each alone), and `nprt submit` (an httpx
client that follows a job's SSE stream with a progress bar and downloads the image). Which
process owns what: nprt.service.processes."""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
from pathlib import Path

from nprt.service.logconfig import add_log_flags, configure_logging

log = logging.getLogger(__name__)

DEFAULT_SERVER = "http://127.0.0.1:8000"
_SETTING_FLAGS = (  # flag, RenderSettings field, type
    ("--width", "width", int), ("--height", "height", int), ("--spp", "spp", int),
    ("--bounces", "bounces", int), ("--shadow-rays", "shadow_rays", int),
    ("--seed", "seed", int), ("--shards", "shards", int), ("--tile-size", "tile_size", int),
    ("--spp-per-pass", "spp_per_pass", int), ("--byte-slack", "byte_slack", float),
)


def add_serve_parsers(subparsers) -> None:
    """Register `serve`, `grpc`, `scheduler` and `submit` on an argparse subparsers
    object."""
    services = (
        ("serve", cmd_serve, "run the REST + gRPC render service",
         "REST (and /docs, dashboard at /) in API worker processes, gRPC in a process of its "
         "own, and a scheduler process that renders; other settings come from NPRT_* "
         "variables.", "; 0: a free one, logged; -1 disables gRPC"),
        ("grpc", cmd_grpc, "run the gRPC server alone",
         "An API worker for gRPC only (`nprt serve` starts one beside its HTTP workers): "
         "stores, reads and watches the jobs of a data directory; renders nothing.", ""))
    for name, func, help_, description, disable in services:
        p = _service_parser(subparsers, name, func, help_, description)
        p.add_argument("--host", default="127.0.0.1", help="bind address")
        p.add_argument("--grpc-port", type=int, default=50051, help="gRPC port" + disable)
    p = subparsers.choices["serve"]
    p.add_argument("--port", type=int, default=8000, help="REST port (0: a free one, logged)")
    p.add_argument("--workers", type=int, default=None,
                   help="HTTP API worker processes sharing the port and the store "
                        "(default: NPRT_API_WORKERS, else 2 on a host with 2 or more cores)")
    p.add_argument("--api-only", action="store_true",
                   help="no scheduler: only store and serve jobs (run `nprt scheduler` once "
                        "per data directory elsewhere)")
    _service_parser(subparsers, "scheduler", cmd_scheduler,
                    "run the scheduler: the process that renders",
                    "Owns Ray, the queue, the job slots and the checkpoints of one data "
                    "directory, and renders the jobs API workers store there.")

    s = subparsers.add_parser("submit", help="submit a render job to a running service",
                              description="SCENE is a demo name (forest, city:small, "
                                          "sculpture:tiny), an uploaded scene id, or a local "
                                          ".glb/.gltf/.json/.zip file to upload first.")
    s.add_argument("scene", help="demo name, uploaded scene id, or a scene file to upload")
    add_server_flags(s)
    for flag, _, typ in _SETTING_FLAGS:
        s.add_argument(flag, type=typ, help="(default: the server's)")
    s.add_argument("--mode", choices=("exact", "proxy", "oracle"),
                   help="traversal policy (default: the server's)")
    s.add_argument("--russian-roulette", action="store_true", default=None,
                   help="end low-throughput paths early")
    s.add_argument("--threshold", type=float, help="proxy visibility threshold")
    s.add_argument("--band", type=float, help="proxy confidence band, secondary rays")
    s.add_argument("--shadow-band", type=float, help="proxy confidence band, shadow rays")
    s.add_argument("--proxy-width", type=int, choices=(16, 32, 64, 128, 256),
                   help="one proxy width for every mesh")
    s.add_argument("--proxy-steps", type=int, help="training budget per proxy, optimiser steps")
    s.add_argument("--frames", type=_frame_pair, metavar="A:B",
                   help="render frames A to B (inclusive) of an animated scene; with -o, "
                        "write each to it (out_####.png: #### = the zero-padded frame)")
    s.add_argument("--wait", action="store_true", help="follow progress until the job ends")
    s.add_argument("-o", "--output", type=Path,
                   help="save the final image here (.png or .exr); implies --wait")
    s.set_defaults(func=cmd_submit)


def add_server_flags(p) -> None:
    """--server, --token and --timeout-s: how a client subcommand reaches the service."""
    p.add_argument("--server", default=os.environ.get("NPRT_SERVER", DEFAULT_SERVER),
                   help="service base URL (NPRT_SERVER)")
    p.add_argument("--token", default=os.environ.get("NPRT_API_TOKEN"),
                   help="bearer token (NPRT_API_TOKEN)")
    p.add_argument("--timeout-s", type=float, default=30.0, help="HTTP request timeout, s")


def _service_parser(subparsers, name: str, func, help_: str, description: str):
    """A subcommand that runs service processes on a data directory, with their flags."""
    p = subparsers.add_parser(name, help=help_, description=description)
    _add_service_flags(p)
    p.set_defaults(func=func)
    return p


def _add_service_flags(p) -> None:
    p.add_argument("--data-dir", type=Path, help="jobs, scenes and database (NPRT_DATA_DIR)")
    p.add_argument("--ray-address", help="Ray cluster to render on (default: local Ray)")
    p.add_argument("--max-jobs", type=int, help="jobs rendering at once "
                                                "(NPRT_MAX_CONCURRENT_JOBS)")
    add_log_flags(p)


def _settings(args: argparse.Namespace):
    from nprt.service.config import ServiceSettings

    overrides = {k: v for k, v in (("data_dir", args.data_dir),
                                   ("ray_address", args.ray_address),
                                   ("max_concurrent_jobs", args.max_jobs)) if v is not None}
    return ServiceSettings(**overrides)


def _log_args(args: argparse.Namespace) -> list[str]:
    """The log flags again, for a child process."""
    out = ["--log-level", args.log_level] if getattr(args, "log_level", None) else []
    return out + (["--log-json"] if getattr(args, "log_json", False) else [])


def cmd_scheduler(args: argparse.Namespace) -> int:
    from nprt.service.processes import run_scheduler

    configure_logging(getattr(args, "log_level", None) or "INFO",
                      getattr(args, "log_json", False))
    return run_scheduler(_settings(args))


def cmd_grpc(args: argparse.Namespace) -> int:
    from nprt.service.grpc_child import run_grpc

    configure_logging(getattr(args, "log_level", None) or "INFO",
                      getattr(args, "log_json", False))
    return run_grpc(_settings(args), args.host, args.grpc_port)


def _start_grpc(args: argparse.Namespace, settings, held):
    """The gRPC child process on the port `held` holds (nprt.service.ports; gRPC's listener
    joins it with SO_REUSEPORT), once it listens (its own process: see grpc_child)."""
    from nprt.service.grpc_child import wait_listening
    from nprt.service.processes import ChildProcess, spawn_child

    port = held.getsockname()[1]
    command = ["grpc", "--host", args.host, "--grpc-port", str(port), *_log_args(args)]
    child = ChildProcess("gRPC server", lambda: spawn_child(settings, command))
    try:
        wait_listening(child.proc, args.host, port)
    except BaseException:
        child.stop()
        raise
    log.info("gRPC on %s:%d (pid %d)", args.host, port, child.proc.pid)
    return child


def default_api_workers() -> int:
    """Two HTTP workers where there are two cores: in a burst of submissions one event loop
    admits them in turn, the last waiting for the CPU of all, and a health check or a
    dashboard's read waits behind them (bench/README.md, "Service under load")."""
    return 2 if (os.cpu_count() or 1) >= 2 else 1


def cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from nprt.service.app import create_app
    from nprt.service.ports import hold_port
    from nprt.service.processes import SchedulerChild

    level = getattr(args, "log_level", None) or "INFO"
    configure_logging(level, getattr(args, "log_json", False))
    settings = _settings(args)
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    # The ports first: a refused one starts nothing (nprt.service.ports).
    rest_held = hold_port(args.host, args.port, "REST")
    grpc_held = None if args.grpc_port < 0 else hold_port(args.host, args.grpc_port, "gRPC")
    scheduler = None if args.api_only else SchedulerChild(settings, _log_args(args))
    grpc = None
    # uvicorn re-raises SIGTERM/SIGINT once it has shut down: exit through `finally` then,
    # so the scheduler stops gracefully (checkpointing) instead of dying with this process.
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda signum, _frame: sys.exit(128 + signum))
    # uvloop and httptools (dependencies) for the HTTP loop: accepting, reading and writing
    # in C. gRPC runs in a process of its own (nprt.service.grpc_child).
    # log_config=None: uvicorn's records go through the root handler (text or JSON) too.
    # access_log: uvicorn formats each request's access line before the logger drops it;
    # above INFO (the benchmarks' WARNING) none would be written.
    options = {"log_level": level.lower(),
               "log_config": None, "timeout_graceful_shutdown": 3, "loop": "uvloop",
               "http": "httptools",
               "access_log": logging.getLevelName(level.upper()) <= logging.INFO}
    try:
        if grpc_held is not None:
            grpc = _start_grpc(args, settings, grpc_held)
        workers = args.workers or settings.api_workers or default_api_workers()
        if workers > 1:  # each worker builds its app from NPRT_* (app_from_env)
            from nprt.service.httpworkers import HttpWorkers

            for name, value in settings.model_dump(exclude_none=True).items():
                os.environ[f"NPRT_{name.upper()}"] = str(value)
            os.environ.pop("NPRT_GRPC_PORT", None)  # gRPC is the child's
            http = HttpWorkers(workers, args.host, rest_held, options)
            log.info("REST on http://%s:%d (%d HTTP workers)", args.host, http.port, workers)
            http.run()
        else:
            rest_held.listen(2048)  # uvicorn's default backlog
            log.info("REST on http://%s:%d (1 HTTP worker)", args.host,
                     rest_held.getsockname()[1])
            uvicorn.Server(uvicorn.Config(create_app(settings), **options)).run(
                sockets=[rest_held])
    finally:
        if grpc is not None:
            grpc.stop()
        if scheduler is not None:
            scheduler.stop()
        for held in (rest_held, grpc_held):
            if held is not None:
                held.close()
    return 0


def cmd_submit(args: argparse.Namespace) -> int:
    import httpx

    from nprt.service.client import ApiError

    try:
        return _submit(args)
    except ApiError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except httpx.TransportError as e:
        print(f"error: cannot reach {args.server}: {e}", file=sys.stderr)
        return 2


def _frame_pair(text: str) -> tuple[int, int]:
    """'A:B' or 'A' -> (first, last) frame."""
    first, _, last = text.partition(":")
    try:
        pair = int(first), int(last or first)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: want A:B (first and last frame)") from None
    if not 0 <= pair[0] <= pair[1]:
        raise argparse.ArgumentTypeError(f"{text!r}: want 0 <= A <= B")
    return pair


def _write_images(client, job_id: str, output: Path, frames: tuple[int, int] | None) -> None:
    """The job's image to output, or each frame's to frame_path(output, f)."""
    from nprt.workers.frames import frame_path

    fmt = output.suffix.lstrip(".") or "png"
    todo = [(output, None)] if frames is None else [
        (Path(frame_path(str(output), f)), f) for f in range(frames[0], frames[1] + 1)]
    for path, f in todo:
        path.write_bytes(client.image(job_id, fmt) if f is None else
                         client.frame(job_id, f, fmt))
        print(f"wrote {path}", file=sys.stderr)


def _submit(args: argparse.Namespace) -> int:
    from nprt.service.client import Client

    body = {field: getattr(args, field) for _, field, _ in _SETTING_FLAGS}
    body |= {"mode": args.mode, "russian_roulette": args.russian_roulette}
    body = {k: v for k, v in body.items() if v is not None}
    knobs = (("threshold", args.threshold), ("band", args.band),
             ("shadow_band", args.shadow_band), ("width", args.proxy_width),
             ("steps", args.proxy_steps))
    proxy = {k: v for k, v in knobs if v is not None}
    if proxy:
        body["proxy"] = proxy
    if args.frames:
        body["frames"] = {"first": args.frames[0], "last": args.frames[1]}
    with Client(args.server, token=args.token, timeout_s=args.timeout_s) as client:
        scene = args.scene
        if Path(scene).is_file():
            scene = client.upload_scene(Path(scene))["id"]
            print(f"uploaded {args.scene} as scene {scene}", file=sys.stderr)
        job = client.submit(scene, body)
        print(job["id"])
        if not (args.wait or args.output):
            return 0
        job = client.follow(job["id"])
        if job["state"] != "succeeded":
            print(f"job {job['id']} {job['state']}: {job.get('error') or ''}", file=sys.stderr)
            return 1
        if args.output:
            _write_images(client, job["id"], args.output, args.frames)
        print(json.dumps({k: job["stats"].get(k) for k in ("wall_s", "rays", "total_bytes")}),
              file=sys.stderr)
    return 0
