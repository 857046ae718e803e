"""The scheduler's renders below the API on the CPU (Linux; elsewhere a step the platform
lacks is skipped).

`nprt scheduler` calls yield_cpu() first thing; every thread it starts and every process it
forks (Ray's GCS, raylet and agents, and the shard workers the raylet forks) inherits the
policy and the nice value. The default (`NPRT_SCHEDULER_CPU=idle`) is SCHED_IDLE in the
session the scheduler was started in, which under `nprt serve` is the API workers' own:
- the kernel preempts a SCHED_IDLE task at once when a normal task of the same group wakes,
  and gives it the smallest weight, so an API request neither waits out a render's time
  slice nor shares the CPU with it;
- with autogroups (the kernel default, /proc/sys/kernel/sched_autogroup_enabled) the CPU is
  shared between sessions before any policy inside them counts, and a session's group is
  never "idle" however idle its tasks are: in a session of its own (the old default,
  `NPRT_SCHEDULER_OWN_SESSION=true`) a render took its session's full share from the API's,
  and SCHED_IDLE, SCHED_BATCH or nice inside it changed nothing (bench/README.md, "A
  render's effect on the API"). In the API's session the API and its renders share one
  share against the host's other sessions, and the renders only get what the API leaves.
`batch` (SCHED_BATCH) only stops renders preempting others; `off` leaves the scheduler as
started. A scheduler started on its own (systemd, another shell) is in another session or
cgroup: give it CPUSchedulingPolicy=idle or a low CPUWeight there.
"""

from __future__ import annotations

import logging
import os

log = logging.getLogger(__name__)

POLICIES = ("idle", "batch", "off")


def _threads() -> list[int]:
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return [0]


def yield_cpu(policy: str, nice: int = 10, own_session: bool = False,
              session_nice: int = 0) -> None:
    """Give this process (every thread of it) and all it starts from now on the CPU
    `policy` ("idle", "batch" or "off") and at least `nice`; with own_session, a session of
    its own whose autogroup runs at `session_nice`. Calling it again changes nothing."""
    if policy not in POLICIES:
        raise ValueError(f"scheduler CPU policy {policy!r}: want one of {', '.join(POLICIES)}")
    if policy == "off":
        return
    kind = getattr(os, "SCHED_IDLE" if policy == "idle" else "SCHED_BATCH", None)
    for tid in _threads():
        try:
            if nice > os.getpriority(os.PRIO_PROCESS, tid):  # Linux: nice is per thread
                os.setpriority(os.PRIO_PROCESS, tid, nice)
            if kind is not None:
                os.sched_setscheduler(tid, kind, os.sched_param(0))
        except (OSError, AttributeError) as e:  # a thread that ended; a platform without it
            log.debug("CPU policy of thread %d: %s", tid, e)
    if not own_session:
        return
    try:
        if os.getsid(0) != os.getpid():
            os.setsid()
    except OSError:  # a process-group leader (started from a shell): its session it stays
        return
    try:
        with open("/proc/self/autogroup", "w") as f:
            f.write(str(session_nice))
    except OSError:
        pass
