"""What the CLI checks before it renders, so a bad option fails in a second instead of after
the render: that the outputs can be written, and that the render fits in memory."""

from __future__ import annotations

import os
import resource
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the CLI imports this module before it knows it will render
    from nprt.workers.settings import RenderSettings

GIB = 1 << 30
# Measured (tracemalloc, bench-free): a reference pass peaks near 600 B per path with four
# shadow rays; PNG output peaks near 63 B per pixel beyond the film. Rounded up.
PATH_WORK_BYTES = 1024
OUTPUT_BYTES_PER_PIXEL = 72
EXR_SUFFIX = ".exr"


class CliError(Exception):
    """A refusal for the user, printed as one line `nprt: <what>: <where>: <why>`."""

    def __init__(self, what: str, where: str, why: str):
        super().__init__(f"{what}: {where}: {why}")


# ---------------------------------------------------------------- outputs


def check_writable(path, flag: str, image: bool = False) -> Path:
    """CliError unless `path` can be written (parents are created on save); `image`: its
    suffix must be one the film can be saved as."""
    path = Path(path)
    where = f"{flag} {path}"
    if image:
        suffix = path.suffix.lower()
        if suffix != EXR_SUFFIX and suffix not in _pil_save_suffixes():
            raise CliError("invalid option", where,
                           f"unknown image type {suffix or '(none)'!r}; use .png or .exr")
    if path.is_symlink() and not path.exists():
        raise CliError("cannot write", where, "is a dangling symlink")
    if path.exists():
        if path.is_dir():
            raise CliError("cannot write", where, "is a directory")
        if not path.is_file():
            raise CliError("cannot write", where, "exists and is not a regular file")
        if not os.access(path, os.W_OK):
            raise CliError("cannot write", where, "permission denied")
        return path
    parent = _nearest_existing(path.parent)
    if not parent.is_dir():
        raise CliError("cannot write", where, f"{parent} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise CliError("cannot write", where, f"directory {parent} is not writable")
    return path


def check_directory(path, flag: str) -> Path:
    """CliError unless `path` is, or can be created as, a writable directory."""
    path = Path(path)
    where = f"{flag} {path}"
    if path.exists() and not path.is_dir():
        raise CliError("cannot write", where, "exists and is not a directory")
    parent = _nearest_existing(path)
    if not parent.is_dir():
        raise CliError("cannot write", where, f"{parent} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise CliError("cannot write", where, f"directory {parent} is not writable")
    return path


def _nearest_existing(path: Path) -> Path:
    path = Path(os.path.abspath(path))
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def _pil_save_suffixes() -> set[str]:
    from PIL import Image

    Image.init()
    return {ext for ext, fmt in Image.registered_extensions().items() if fmt in Image.SAVE}


# ---------------------------------------------------------------- memory


@dataclass(frozen=True)
class MemoryEstimate:
    """Bytes a render holds at its peak, by part."""

    film_bytes: int  # per-pixel radiance sums and sample counts
    output_bytes: int  # the image and its encoding, while the film is alive
    inflight_bytes: int  # tile sums of the passes in flight (passes are never listed)
    pass_work_bytes: int  # the ray batches of one pass

    @property
    def total_bytes(self) -> int:
        return self.film_bytes + self.output_bytes + self.inflight_bytes + self.pass_work_bytes

    def describe(self) -> str:
        return (f"~{_gib(self.total_bytes)} (film {_gib(self.film_bytes)}, image output "
                f"{_gib(self.output_bytes)}, passes in flight {_gib(self.inflight_bytes)}, "
                f"per-pass work {_gib(self.pass_work_bytes)})")


def estimate_memory(s: RenderSettings) -> MemoryEstimate:
    """Peak memory of rendering `s` in this process (the film lives in the driver)."""
    from nprt.workers.film import ACCUM_DTYPE

    pixels = s.width * s.height
    film = pixels * (3 * ACCUM_DTYPE().itemsize + 8)  # sums (3 float64) + samples (int64)
    tile_pixels = min(s.tile_size, s.width) * min(s.tile_size, s.height)
    k = max(s.shards, 1)
    window = 1
    if s.shards:  # the coordinator imports Ray, and Ray gRPC: not for a reference render
        from nprt.workers.passes import count_tiles
        from nprt.workers.runtime.coordinator import live_window

        window = live_window(k, count_tiles(s))
    inflight = window * k * tile_pixels * 3 * ACCUM_DTYPE().itemsize  # one part per shard
    return MemoryEstimate(film, pixels * OUTPUT_BYTES_PER_PIXEL, inflight,
                          tile_pixels * s.spp_per_pass * PATH_WORK_BYTES)


def check_memory(s: RenderSettings, available_bytes: int | None = None) -> MemoryEstimate:
    """CliError when the render would not fit in the memory available to this process."""
    est = estimate_memory(s)
    available = available_memory_bytes() if available_bytes is None else available_bytes
    if available is not None and est.total_bytes > available:
        raise CliError("render too large", f"--width {s.width} --height {s.height} --spp {s.spp}",
                       f"the render needs {est.describe()}, but only {_gib(available)} of "
                       f"memory is available")
    return est


def available_memory_bytes() -> int | None:
    """The least of: the system's available memory, the cgroup's headroom, and the
    address-space limit (ulimit -v) less what this process maps. None when unknown."""
    limits = [x for x in (_meminfo_available(), _cgroup_headroom(), _rlimit_headroom())
              if x is not None]
    return max(0, min(limits)) if limits else None


def _meminfo_available() -> int | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _cgroup_headroom() -> int | None:
    for limit_file, usage_file in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                                   ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                                    "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:
            limit = Path(limit_file).read_text().strip()
            usage = int(Path(usage_file).read_text().strip())
        except (OSError, ValueError):
            continue
        if limit.isdigit() and int(limit) < (1 << 60):  # v1 writes a huge number for none
            return int(limit) - usage
    return None


def _rlimit_headroom() -> int | None:
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft == resource.RLIM_INFINITY:
        return None
    try:
        mapped = int(Path("/proc/self/statm").read_text().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        mapped = 0
    return soft - mapped


def _gib(n: int) -> str:
    return f"{n / GIB:.1f} GiB" if n >= GIB / 10 else f"{n / (1 << 20):.1f} MiB"
