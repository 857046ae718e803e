"""One Ray per process, shared by every pool and coordinator in it: started here (and shut
down by the last user) unless the process already joined one.

Ray stays off the console unless nprt logs at DEBUG: no dashboard (`include_dashboard`),
worker output stays in Ray's log files (`log_to_driver`), and Ray's own Python logger
shows errors only (its start-up notices, such as the one that token authentication is on,
are not for nprt's users). At DEBUG, Ray logs at INFO and forwards worker output.

`include_dashboard=False` turns off the dashboard's UI and HTTP server only: Ray 2.60
still starts a headless `dashboard.py` (usage stats) and the raylet's dashboard agent
(runtime environments, metrics), and offers no switch for either (ray-project/ray#17770;
PR #19420 declined one)."""

from __future__ import annotations

import logging
import threading

import ray

_RAY_LOCK = threading.Lock()
_RAY_USERS = 0  # live pools on a Ray that this module started
_RAY_OWNED = False


def ray_console() -> dict:
    """The ray.init arguments that decide what Ray prints, by nprt's own level (the root
    logger's: `nprt --log-level debug` lowers it to DEBUG)."""
    debug = logging.getLogger().isEnabledFor(logging.DEBUG)
    return {"logging_level": logging.INFO if debug else logging.ERROR, "log_to_driver": debug}


def _init(address: str | None) -> None:
    ray.init(address=address, include_dashboard=False, **ray_console())


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
