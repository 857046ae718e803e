"""Whether numba's on-disk cache holds the compiled kernels of `nprt.workers` (the modules
of `kernels/`, and any other module with a kernel of its own, such as
`routing/proxy_pairs.py`), read from the file system without importing numba (the driver
never does), so that a render can say before it starts that it will first compile them."""

from __future__ import annotations

import functools
import logging
import os
import re
from pathlib import Path

log = logging.getLogger(__name__)

WORKERS = Path(__file__).resolve().parent
KERNELS = WORKERS / "kernels"
# CPU seconds to compile the kernels with an empty cache: 34-44 s for a 16x12 reference render
# of forest:tiny (bench/render/bench_first_run.py); 62 s for those and the shards' own, exact
# and proxy (tests/warm_kernels.py); 2 cores, 2026-11-27. A pool compiles on one shard a
# node (`pool.first_cold_per_node`).
COLD_COMPILE_CPU_S = {"reference": 40, "distributed": 60}
# The Wald step routes between shards, and buckets sorts rays leaving for them: the
# reference never runs either.
SHARD_ONLY = ("nearest", "buckets")
PROXY_ONLY = ("proxy_pairs",)  # only proxy mode asks the proxies


@functools.cache
def _sources() -> tuple[Path, ...]:
    """Every module of nprt.workers with a function numba compiles on its own (read once a
    process: the sources do not change under a running renderer)."""
    return tuple(src for src in sorted(WORKERS.rglob("*.py"))
                 if "__pycache__" not in src.parts and _compiles_alone(src.read_text()))


def _cache_dirs(src: Path) -> list[Path]:
    """Where numba looks for src's index files: under NUMBA_CACHE_DIR, one folder per
    source folder, named after it and a hash of its path; else the folder's __pycache__."""
    root = os.environ.get("NUMBA_CACHE_DIR")
    if root:
        return sorted(Path(root).glob(f"{src.parent.name}_*"))
    return [src.parent / "__pycache__"]


def cold_kernel_modules() -> list[str]:
    """Compiled modules (file stems) with no cache index as new as their source: their
    functions compile on first use."""
    cold = []
    for src in _sources():
        newest = max((f.stat().st_mtime for d in _cache_dirs(src) if d.is_dir()
                      for f in d.glob(src.stem + ".*.nbi")), default=None)
        if newest is None or newest < src.stat().st_mtime:
            cold.append(src.stem)
    return cold


def _compiles_alone(source: str) -> bool:
    """Whether a kernel module has a function numba compiles (and caches) on its own: one
    whose every @njit is inline="always" is compiled inside its callers and never writes a
    cache index, so it would look cold forever."""
    decorators = re.findall(r"^[ \t]*@njit(?:\(([^)]*)\))?[ \t]*$", source, re.M)
    return any('inline="always"' not in args for args in decorators)


def cold_modules_run_by(distributed: bool, proxies: bool = False) -> list[str]:
    """`cold_kernel_modules` that a render of this kind compiles: a module it never runs
    would look cold before every render."""
    return [m for m in cold_kernel_modules() if (distributed or m not in SHARD_ONLY)
            and (proxies or m not in PROXY_ONLY)]


def note_cold_compile(where: str, distributed: bool, proxies: bool = False) -> bool:
    """Log, before a render whose kernels are not cached yet, that it compiles them first
    and about how long that takes. Returns whether it did."""
    cold = cold_modules_run_by(distributed, proxies)
    if cold:
        log.warning("compiling the numba kernels before the first %s (%s): about %d s of CPU, "
                    "once; later runs load them from the cache", where, ", ".join(cold),
                    COLD_COMPILE_CPU_S["distributed" if distributed else "reference"])
    return bool(cold)
