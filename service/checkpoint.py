"""Per-job files: the resumable film checkpoint, written every few seconds, and the final
outputs.

A checkpoint is sums-<n>.npy + samples-<n>.npy + checkpoint.json; the json is written
last, with os.replace, so it only ever names a complete pair. It records which passes the
film holds: every pass below `next_pass` plus the few in `done` (passes finish out of
order), so a restart re-renders exactly the others and counts no sample twice.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np

from nprt.workers.render import ResumeState

CHECKPOINT = "checkpoint.json"


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write to a temp file in the same directory, then rename over `path`: readers and a
    restart after kill -9 see the old or the new file, never a torn one."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_save_npy(path: Path, arr: np.ndarray) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            np.save(f, arr)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def save_checkpoint(job_dir: Path, next_pass: int, sums: np.ndarray, samples: np.ndarray,
                    stats: dict, done: list[int] | tuple = ()) -> int:
    """sums : (h * w, 3) float64; samples : (h * w,) int64; stats : RenderStats.to_dict();
    done : finished passes at or above next_pass. Returns the bytes written."""
    tag = f"{next_pass}-{len(done)}"
    atomic_save_npy(job_dir / f"sums-{tag}.npy", sums)
    atomic_save_npy(job_dir / f"samples-{tag}.npy", samples)
    meta = json.dumps({"next_pass": next_pass, "done": sorted(done), "tag": tag,
                       "stats": stats}).encode()
    atomic_write_bytes(job_dir / CHECKPOINT, meta)
    # Older pairs are garbage only once the json no longer names them.
    for old in list(job_dir.glob("sums-*.npy")) + list(job_dir.glob("samples-*.npy")):
        if old.stem.split("-", 1)[1] != tag:
            old.unlink(missing_ok=True)
    return int(sums.nbytes + samples.nbytes + len(meta))


def load_checkpoint(job_dir: Path) -> ResumeState | None:
    path = job_dir / CHECKPOINT
    if not path.exists():
        return None
    meta = json.loads(path.read_text())
    n = int(meta["next_pass"])
    tag = meta.get("tag", str(n))
    return ResumeState(next_pass=n, sums=np.load(job_dir / f"sums-{tag}.npy"),
                       samples=np.load(job_dir / f"samples-{tag}.npy"),
                       stats=meta.get("stats", {}), done=[int(i) for i in meta.get("done", [])])


def read_checkpoint(job_dir: Path, tries: int = 3) -> ResumeState | None:
    """load_checkpoint from another process than the writer: a pair named by the json can
    be replaced between reading the json and the arrays, so a missing file means "read
    again"."""
    for attempt in range(tries):
        try:
            return load_checkpoint(job_dir)
        except (FileNotFoundError, ValueError, EOFError):
            if attempt == tries - 1:
                raise
    return None


def frame_file(job_dir: Path, frame: int, fmt: str) -> Path:
    """Where a frames job stores one finished frame's image."""
    return job_dir / "frames" / f"{frame:05d}.{fmt}"


def clear_checkpoint(job_dir: Path) -> None:
    (job_dir / CHECKPOINT).unlink(missing_ok=True)
    for old in list(job_dir.glob("sums-*.npy")) + list(job_dir.glob("samples-*.npy")):
        old.unlink(missing_ok=True)
