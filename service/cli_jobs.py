"""`nprt jobs list|show|cancel|delete|logs|wait`: follow and steer a running service's jobs
from the command line (REST through nprt.service.client)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from datetime import datetime

from nprt.service.cli_serve import add_server_flags
from nprt.service.preflight import CliError

STATES = ("queued", "preparing", "running", "succeeded", "failed", "canceled")
TERMINAL = frozenset(STATES[3:])
ID_LENGTH = 32  # a full job id, hex
PREFIX_SCAN = 500  # newest jobs searched for a short id prefix


def add_jobs_parser(subparsers) -> None:
    jobs = subparsers.add_parser("jobs", help="list, inspect, cancel, follow jobs of a server",
                                 description="Job ids may be shortened to any unique prefix "
                                             f"among the newest {PREFIX_SCAN} jobs.")
    sub = jobs.add_subparsers(dest="jobs_command", required=True)

    p = sub.add_parser("list", help="jobs, newest first")
    p.add_argument("--state", choices=STATES, help="only jobs in this state")
    p.add_argument("--limit", type=int, default=20, help="jobs to show")
    p.add_argument("--offset", type=int, default=0, help="newest jobs to skip")
    p.add_argument("--json", action="store_true", help="print the JSON page")
    p.set_defaults(func=cmd_list)

    p = sub.add_parser("show", help="one job: settings, times, progress, statistics")
    p.add_argument("job", help="job id or unique prefix")
    p.add_argument("--json", action="store_true", help="print the job's JSON")
    p.set_defaults(func=cmd_show)

    for name, func, what in (("cancel", cmd_cancel, "stop a queued or running job"),
                             ("delete", cmd_delete, "delete a finished job and its files")):
        p = sub.add_parser(name, help=what)
        p.add_argument("job", help="job id or unique prefix")
        p.set_defaults(func=func)

    p = sub.add_parser("logs", help="the job's log (job.log)")
    p.add_argument("job", help="job id or unique prefix")
    p.add_argument("-f", "--follow", action="store_true",
                   help="keep printing new lines until the job ends")
    p.set_defaults(func=cmd_logs)

    p = sub.add_parser("wait", help="wait until the job ends; exit 0 if it succeeded, else 1")
    p.add_argument("job", help="job id or unique prefix")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_wait)

    for p in sub.choices.values():
        add_server_flags(p)


def _run(args: argparse.Namespace, body) -> int:
    """Call body(client, job id or None) and turn API and network errors into one line."""
    import httpx

    from nprt.service.client import ApiError, Client

    try:
        with Client(args.server, token=args.token, timeout_s=args.timeout_s) as client:
            job_id = _resolve(client, args.job) if hasattr(args, "job") else None
            return int(body(client, job_id) or 0)
    except ApiError as e:
        raise CliError("server refused", args.server, str(e)) from None
    except httpx.TransportError as e:
        raise CliError("cannot reach the server", args.server, str(e) or type(e).__name__
                       ) from None


def _resolve(client, prefix: str) -> str:
    if len(prefix) >= ID_LENGTH:
        return prefix
    page = client.jobs(limit=PREFIX_SCAN)["data"]
    found = [j["id"] for j in page if j["id"].startswith(prefix.lower())]
    if len(found) != 1:
        why = "no job" if not found else f"{len(found)} jobs ({', '.join(found[:3])}...)"
        raise CliError("job id", prefix, f"{why} among the newest {PREFIX_SCAN} start with it")
    return found[0]


def summary(settings: dict) -> str:
    """'64x48 4spp exact' or '64x48 4spp proxy K=2'."""
    s = settings
    out = f"{s['width']}x{s['height']} {s['spp']}spp {s['mode']}"
    return out + (f" K={s['shards']}" if s["shards"] else " ref")


def duration_s(job: dict, now: float | None = None) -> float | None:
    """Seconds from start to finish (or to now while it runs); None before it starts."""
    if not job.get("started_at"):
        return None
    end = _ts(job["finished_at"]) if job.get("finished_at") else (now or time.time())
    return max(0.0, end - _ts(job["started_at"]))


def _ts(iso: str) -> float:
    return datetime.fromisoformat(iso).timestamp()


def _age(job: dict, now: float) -> str:
    s = now - _ts(job["created_at"])
    for unit, size in (("d", 86400), ("h", 3600), ("m", 60)):
        if s >= size:
            return f"{s / size:.0f}{unit}"
    return f"{s:.0f}s"


def cmd_list(args: argparse.Namespace) -> int:
    def body(client, _):
        page = client.jobs(args.offset, args.limit, args.state)
        if args.json:
            print(json.dumps(page, indent=1))
            return 0
        now = time.time()
        rows = [("ID", "STATE", "SCENE", "SETTINGS", "DONE", "AGE", "DURATION")]
        for j in page["data"]:
            d = duration_s(j, now)
            rows.append((j["id"][:8], j["state"], j["scene"][:24], summary(j["settings"]),
                         f"{100 * j['progress']:.0f}%", _age(j, now),
                         "-" if d is None else f"{d:.1f}s"))
        widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
        for r in rows:
            print("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip())
        shown = len(page["data"])
        print(f"{shown} of {page['count']} job(s), from offset {args.offset}", file=sys.stderr)
        return 0

    return _run(args, body)


def cmd_show(args: argparse.Namespace) -> int:
    def body(client, job_id):
        job = client.job(job_id)
        if args.json:
            print(json.dumps(job, indent=1))
            return 0
        d = duration_s(job)
        stats = job.get("stats") or {}
        lines = [("id", job["id"]), ("scene", job["scene"]), ("state", job["state"]),
                 ("settings", summary(job["settings"])),
                 ("progress", f"{job['passes_done']} of {job['passes_total']} passes"),
                 ("created", job["created_at"]), ("started", job.get("started_at") or "-"),
                 ("finished", job.get("finished_at") or "-"),
                 ("duration", "-" if d is None else f"{d:.2f} s")]
        if job.get("error"):
            lines.append(("error", job["error"]))
        if "wall_s" in stats:
            lines.append(("render wall", f"{stats['wall_s']:.2f} s"))
        if stats.get("rays"):
            lines.append(("rays", f"{sum(stats['rays'].values()):,}"))
        if "total_bytes" in stats:
            lines.append(("bytes moved", f"{stats['total_bytes']:,}"))
        for k, v in lines:
            print(f"{k:>12}  {v}")
        return 0

    return _run(args, body)


def cmd_cancel(args: argparse.Namespace) -> int:
    return _run(args, lambda client, job_id: print(
        f"{job_id} {client.cancel(job_id)['state']}"))


def cmd_delete(args: argparse.Namespace) -> int:
    def body(client, job_id):
        client.delete(job_id)
        print(f"{job_id} deleted")

    return _run(args, body)


def cmd_logs(args: argparse.Namespace) -> int:
    def body(client, job_id):
        if not args.follow:
            sys.stdout.write(client.logs(job_id))
            return 0
        for line in client.follow_logs(job_id):
            print(line, flush=True)
        return 0

    return _run(args, body)


def cmd_wait(args: argparse.Namespace) -> int:
    def body(client, job_id):
        job = client.follow(job_id, progress=not args.quiet and sys.stderr.isatty())
        print(f"{job_id} {job['state']}" + (f": {job['error']}" if job.get("error") else ""))
        return 0 if job["state"] == "succeeded" else 1

    return _run(args, body)
