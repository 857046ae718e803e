"""One Ray per process, shared by every pool and coordinator in it: started here (and shut
down by the last user) unless the process already joined one.

Ray stays off the console unless nprt logs at DEBUG: no dashboard (`include_dashboard`),
worker output stays in Ray's log files (`log_to_driver`), and Ray's own Python logger
shows errors only (its start-up notices, such as the one that token authentication is on,
are not for nprt's users). At DEBUG, Ray logs at INFO and forwards worker output.

`include_dashboard=False` turns off the dashboard's UI and HTTP server only: Ray 2.60
still starts a headless `dashboard.py` (usage stats) and the raylet's dashboard agent
(runtime environments, metrics), and offers no switch for either (ray-project/ray#17770;
PR #19420 declined one).

Per-call settings, measured with `bench/render/bench_ray_calls.py` (two threaded actors
exchanging nprt parcels; whole-process CPU from /proc, Ray's threads and the raylet
counted):
- `max_direct_call_object_size` (`RAY_SYSTEM_CONFIG`): a call argument up to this size
  travels inline in the call (gRPC) instead of through the object store. Ray's default,
  100 kB, sends a parcel of more than about 1,100 rays (92 bytes a ray) through plasma:
  a put, a seal, a pin and a free in the sender's raylet, and the receiver's fetch,
  together 1.1-1.4 ms of CPU more than inline for a 460 kB parcel (5,000 rays), about
  1 ms of it in the raylet. Ray caps the inlined bytes of one call at
  `task_rpc_inlined_bytes_limit` (10 MB), so a larger parcel still goes through plasma.
  A system config is fixed when Ray starts: it applies to a Ray that nprt starts here;
  a cluster gets it from `ray start --head --system-config` (deploy/cluster.yaml, and
  every node fetches the head's).
- Task events are off for the shard actors (`enable_task_events=False`, `pool.py`): Ray
  records each call for its dashboard and state API, which nprt does not read (its job
  statistics come from the shards' poll replies). With `deliver` returning no ref
  (`remote.py`) this cut 0-21 % of the CPU per 100-ray parcel in three runs; either
  alone was within the run-to-run noise. Turning metrics collection off
  (`enable_metrics_collection`) changed nothing measurable, so it stays on."""

from __future__ import annotations

import logging
import threading
from types import MappingProxyType

import ray
from ray._private.services import canonicalize_bootstrap_address

_RAY_LOCK = threading.Lock()
_RAY_USERS = 0  # live pools on a Ray that this module started
_RAY_OWNED = False


def ray_console() -> dict:
    """The ray.init arguments that decide what Ray prints, by nprt's own level (the root
    logger's: `nprt --log-level debug` lowers it to DEBUG)."""
    debug = logging.getLogger().isEnabledFor(logging.DEBUG)
    return {"logging_level": logging.INFO if debug else logging.ERROR, "log_to_driver": debug}


# Ray's system config for a Ray that nprt starts (see the module docstring).
# Read-only: ray.init adds its own entries (object spilling, with the session's directory)
# to the dict it is given, so every caller passes a copy (`dict(RAY_SYSTEM_CONFIG)`).
RAY_SYSTEM_CONFIG = MappingProxyType({"max_direct_call_object_size": 1 << 20})


def _starts_local(address: str | None) -> bool:
    """Whether ray.init(address) would start a Ray (and so accept a system config) rather
    than join one: Ray's own resolution of None, "auto", "local" and RAY_ADDRESS. Its
    warnings (several Rays on this host) are ray.init's to print, at the level it sets."""
    services_log = logging.getLogger("ray._private.services")
    level = services_log.level
    services_log.setLevel(logging.ERROR)
    try:
        return canonicalize_bootstrap_address(address) is None
    except Exception:  # no cluster where one was named: ray.init says so itself
        return False
    finally:
        services_log.setLevel(level)


def _init(address: str | None) -> None:
    config = dict(RAY_SYSTEM_CONFIG) if _starts_local(address) else None
    ray.init(address=address, include_dashboard=False, _system_config=config, **ray_console())


def ensure_ray(address: str | None = None) -> bool:
    """Join `address`, or start a local Ray. Returns True when this call started it."""
    with _RAY_LOCK:
        if ray.is_initialized():
            return False
        _init(address)
        return True


def acquire_ray(address: str | None) -> None:
    """Pools in several threads (the service runs jobs concurrently) share one Ray; the
    last one out shuts down a Ray that a pool started."""
    global _RAY_USERS, _RAY_OWNED
    with _RAY_LOCK:
        if not ray.is_initialized():
            _init(address)
            _RAY_OWNED = True
        _RAY_USERS += 1


def release_ray() -> None:
    global _RAY_USERS, _RAY_OWNED
    with _RAY_LOCK:
        _RAY_USERS -= 1
        if _RAY_USERS == 0 and _RAY_OWNED:
            ray.shutdown()
            _RAY_OWNED = False
