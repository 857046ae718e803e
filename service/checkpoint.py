"""Per-job files: the resumable film checkpoint after each pass, and the final outputs.

A checkpoint is sums-<n>.npy + samples-<n>.npy + checkpoint.json; the json is written
last, with os.replace, so it only ever names a complete pair (n = next pass to render).
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np

from workers.render import ResumeState

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
                    stats: dict) -> None:
    """sums : (h * w, 3) float64; samples : (h * w,) int64; stats : RenderStats.to_dict()."""
    atomic_save_npy(job_dir / f"sums-{next_pass}.npy", sums)
    atomic_save_npy(job_dir / f"samples-{next_pass}.npy", samples)
    meta = {"next_pass": next_pass, "stats": stats}
    atomic_write_bytes(job_dir / CHECKPOINT, json.dumps(meta).encode())
    # Older pairs are garbage only once the json no longer names them.
    for old in list(job_dir.glob("sums-*.npy")) + list(job_dir.glob("samples-*.npy")):
        if old.stem.rsplit("-", 1)[1] != str(next_pass):
            old.unlink(missing_ok=True)


def load_checkpoint(job_dir: Path) -> ResumeState | None:
    path = job_dir / CHECKPOINT
    if not path.exists():
        return None
    meta = json.loads(path.read_text())
    n = int(meta["next_pass"])
    return ResumeState(next_pass=n, sums=np.load(job_dir / f"sums-{n}.npy"),
                       samples=np.load(job_dir / f"samples-{n}.npy"),
                       stats=meta.get("stats", {}))


def clear_checkpoint(job_dir: Path) -> None:
    (job_dir / CHECKPOINT).unlink(missing_ok=True)
    for old in list(job_dir.glob("sums-*.npy")) + list(job_dir.glob("samples-*.npy")):
        old.unlink(missing_ok=True)
