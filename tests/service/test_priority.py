"""Renders yield the CPU to the API: `nprt serve`'s scheduler and everything it starts
(Ray's GCS, raylet, agents and shard workers) run as SCHED_IDLE at nice >= 10, every thread
of them, in the API's session (its autogroup: the kernel shares the CPU between autogroups
before a policy counts); NPRT_SCHEDULER_CPU=off leaves the scheduler as `nprt serve`
started it. Checked on the processes' /proc entries, not by
timing (bench/service/bench_render_effect.py measures the effect)."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from nprt.service.config import ServiceSettings
from nprt.service.priority import yield_cpu
from tests.service.helpers import REPO, start_serve, wait_for

# Far more passes than the checks take; canceled after them.
SHARDED = {"scene": "forest:tiny", "width": 32, "height": 32, "spp": 4096, "bounces": 1,
           "tile_size": 32, "spp_per_pass": 1, "shards": 2}


@contextlib.contextmanager
def _serve(tmp_path: Path, **env: str):
    """`nprt serve` (REST only) on a fresh data dir, with env added; yields (process, URL)
    once it answers, and stops it on the way out."""
    # The defaults, whatever conftest set for the other tests' services.
    environ = {**os.environ, "PYTHONPATH": str(REPO), "NPRT_SCHEDULER_CPU": "idle",
               "NPRT_SCHEDULER_OWN_SESSION": "false", **env}
    environ.pop("NPRT_API_TOKEN", None)
    proc, url = start_serve(["--grpc-port", "-1", "--data-dir", str(tmp_path / "data")],
                            tmp_path / "serve.log", environ)
    try:
        yield proc, url
    finally:
        proc.terminate()
        proc.wait(120)


def _stat(pid: int, tid: int | None = None) -> tuple[str, list[str]]:
    path = f"/proc/{pid}/stat" if tid is None else f"/proc/{pid}/task/{tid}/stat"
    text = Path(path).read_text()
    return text.split("(", 1)[1].rsplit(")", 1)[0], text.rsplit(")", 1)[1].split()


def _children(pid: int) -> list[int]:
    return [int(c) for t in os.listdir(f"/proc/{pid}/task")
            for c in Path(f"/proc/{pid}/task/{t}/children").read_text().split()]


def _tree(pid: int) -> list[int]:
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo += _children(p)
    return out


def _scheduler(serve: subprocess.Popen, data: Path) -> int:
    """The scheduler child's pid, once it has started (taken its lock)."""
    pid = wait_for(lambda: next((c for c in _children(serve.pid) if b"scheduler" in Path(
        f"/proc/{c}/cmdline").read_bytes()), None), 30, what="the scheduler child")
    wait_for(lambda: (data / "scheduler.lock").exists(), 60, what="the scheduler's start")
    return pid


def _autogroup(pid: int) -> str | None:
    """The process's autogroup, or None where none applies: the kernel prints nothing when
    the task's group is a cgroup of its own (in a container, for example) or autogroups are
    off, and sessions then play no part in CPU shares."""
    fields = Path(f"/proc/{pid}/autogroup").read_text().split()
    return fields[0] if fields else None


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux scheduling")
def test_scheduler_and_the_ray_it_starts_run_as_idle_work_in_the_api_session(tmp_path):
    with _serve(tmp_path) as (serve, url):
        job = httpx.post(f"{url}/v1/jobs", json=SHARDED, timeout=10).json()
        wait_for(lambda: httpx.get(f"{url}/v1/jobs/{job['id']}").json()["passes_done"] >= 1,
                 180, what="a pass of the K = 2 render")
        scheduler = _scheduler(serve, tmp_path / "data")
        group = _autogroup(serve.pid)
        seen = set()
        for pid in _tree(scheduler):
            try:
                name, fields = _stat(pid)
                tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
                assert os.getsid(pid) == os.getsid(serve.pid), name
                assert _autogroup(pid) == group, name
                for tid in tids:
                    _, thread = _stat(pid, tid)
                    assert int(thread[38]) == os.SCHED_IDLE, (name, tid)
                    assert int(thread[16]) >= 10, (name, tid)
            except FileNotFoundError:  # a process or thread that ended meanwhile
                continue
            seen.add(name)
        assert {"raylet", "gcs_server", "ray::ShardActor"} <= seen, seen
        # The API keeps the normal policy.
        assert os.sched_getscheduler(serve.pid) == os.SCHED_OTHER
        httpx.post(f"{url}/v1/jobs/{job['id']}/cancel", timeout=10)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux scheduling")
def test_scheduler_cpu_off_leaves_the_scheduler_as_serve_started_it(tmp_path):
    with _serve(tmp_path, NPRT_SCHEDULER_CPU="off") as (serve, _):
        scheduler = _scheduler(serve, tmp_path / "data")
        assert os.sched_getscheduler(scheduler) == os.SCHED_OTHER
        assert os.getpriority(os.PRIO_PROCESS, scheduler) == os.getpriority(
            os.PRIO_PROCESS, serve.pid)
        assert os.getsid(scheduler) == os.getsid(serve.pid)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux scheduling")
def test_scheduler_own_session_gives_it_a_session_and_autogroup_of_its_own(tmp_path):
    with _serve(tmp_path, NPRT_SCHEDULER_OWN_SESSION="true") as (serve, _):
        scheduler = _scheduler(serve, tmp_path / "data")
        assert os.sched_getscheduler(scheduler) == os.SCHED_IDLE
        assert os.getsid(scheduler) == scheduler != os.getsid(serve.pid)
        if _autogroup(serve.pid) is not None:  # a new session is a new autogroup
            assert _autogroup(scheduler) != _autogroup(serve.pid)


def test_unknown_scheduler_cpu_policy_is_refused():
    with pytest.raises(ValueError, match="want one of idle, batch, off"):
        yield_cpu("lowest")
    with pytest.raises(ValueError, match="scheduler_cpu"):
        ServiceSettings(scheduler_cpu="lowest")
