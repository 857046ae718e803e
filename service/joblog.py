"""A per-job log file: records from the thread rendering that job (and any record naming the
job's id) go to <job_dir>/job.log; readers take it in whole lines from a byte offset."""

from __future__ import annotations

import logging
import threading
from contextlib import contextmanager
from pathlib import Path

FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
JOB_LOG_LEVEL = logging.INFO
LOG_NAME = "job.log"
# One read of a log returns at most this much, so a huge log cannot fill a response.
MAX_READ_BYTES = 1 << 20

_lift_lock = threading.Lock()


# Loggers whose records from other threads join a job's log when they name the job (a
# cancel from the API thread); access logs of its URLs do not.
NPRT_LOGGERS = ("service", "workers", "proxies", "scene")


class _JobFilter(logging.Filter):
    """The job's thread (worker threads are shared between jobs, so it is the thread running
    this job now), or an nprt record from another thread that names the job."""

    def __init__(self, thread_id: int, job_id: str):
        super().__init__()
        self.thread_id, self.job_id = thread_id, job_id

    def filter(self, record: logging.LogRecord) -> bool:
        if record.thread == self.thread_id:
            return True
        return (record.name.split(".", 1)[0] in NPRT_LOGGERS
                and self.job_id in record.getMessage())


def _ensure_records_exist(level: int) -> None:
    """Records below the root logger's level are never created, so no handler could write
    them. Lower the root level to `level` once, and give each root handler that had no level
    of its own the old one: what reaches the console stays as it was."""
    root = logging.getLogger()
    with _lift_lock:
        old = root.getEffectiveLevel()
        if old <= level:
            return
        for h in root.handlers:
            if h.level == logging.NOTSET:
                h.setLevel(old)
        root.setLevel(level)


@contextmanager
def job_log(path: Path):
    """Attach a file handler at JOB_LOG_LEVEL to the root logger for the current thread;
    the job id is the name of the log's folder (<jobs_dir>/<id>/job.log)."""
    _ensure_records_exist(JOB_LOG_LEVEL)
    handler = logging.FileHandler(path, encoding="utf-8")
    handler.setLevel(JOB_LOG_LEVEL)
    handler.setFormatter(logging.Formatter(FORMAT))
    handler.addFilter(_JobFilter(threading.get_ident(), path.parent.name))
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        yield
    finally:
        root.removeHandler(handler)
        handler.close()


def read_lines(path: Path, offset: int = 0, max_bytes: int = MAX_READ_BYTES
               ) -> list[tuple[str, int]]:
    """Whole lines of the log from byte `offset` on, each with the byte offset just after
    it (where a reader resumes); a line still being written waits for the next read. No
    file yet: []."""
    try:
        with path.open("rb") as f:
            f.seek(offset)
            data = f.read(max_bytes)
    except FileNotFoundError:
        return []
    if b"\n" not in data and len(data) == max_bytes:  # a line longer than max_bytes: cut
        return [(data.decode("utf-8", errors="replace"), offset + len(data))]
    out, start = [], 0
    while (stop := data.find(b"\n", start)) >= 0:
        out.append((data[start:stop].decode("utf-8", errors="replace"), offset + stop + 1))
        start = stop + 1
    return out


class LogTail:
    """Follows one job log by polling: new lines each poll, and done once the job is
    terminal and the log has been quiet for grace_s (the job thread logs its last lines just
    after it stores the final state)."""

    def __init__(self, path: Path, offset: int = 0, grace_s: float = 1.0):
        self.path, self.offset, self.grace_s = path, offset, grace_s
        self._quiet_since: float | None = None

    def poll(self, terminal: bool, now_s: float) -> tuple[list[tuple[str, int]], bool]:
        """(new lines with their end offsets, done); now_s: a monotonic clock."""
        lines = read_lines(self.path, self.offset)
        if lines:
            self.offset = lines[-1][1]
        if lines or not terminal:
            self._quiet_since = None
            return lines, False
        if self._quiet_since is None:
            self._quiet_since = now_s
        return lines, now_s - self._quiet_since >= self.grace_s
