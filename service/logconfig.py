"""Process-wide logging for the `nprt` command: one stderr handler at the chosen level, as
text or as one JSON object per line; the root logger stays at INFO or below so that each
job's job.log gets its records whatever the console shows."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from datetime import UTC, datetime

from nprt.service.joblog import JOB_LOG_LEVEL

TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")


class JsonFormatter(logging.Formatter):
    """One JSON object per record: time (ISO 8601, UTC), level, logger, message, thread,
    and exc (the formatted traceback) when there is one."""

    def format(self, record: logging.LogRecord) -> str:
        out = {"time": datetime.fromtimestamp(record.created, UTC).isoformat(),
               "level": record.levelname, "logger": record.name,
               "message": record.getMessage(), "thread": record.threadName}
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out, default=str)


def configure_logging(level: str = "WARNING", json_lines: bool = False) -> None:
    """Install one stderr handler at `level` (a name from LEVELS, any case) on the root
    logger, replacing the one an earlier call installed; other handlers stay."""
    name = level.upper()
    if name not in LEVELS:
        raise ValueError(f"unknown log level {level!r}; expected one of {', '.join(LEVELS)}")
    console = logging.StreamHandler(sys.stderr)
    console.setLevel(name)
    console.setFormatter(JsonFormatter() if json_lines else logging.Formatter(TEXT_FORMAT))
    console.nprt_console = True  # marks the handler the next call replaces
    root = logging.getLogger()
    for h in list(root.handlers):
        if getattr(h, "nprt_console", False):
            root.removeHandler(h)
    root.addHandler(console)
    root.setLevel(min(logging.getLevelName(name), JOB_LOG_LEVEL))


def add_log_flags(p: argparse.ArgumentParser, global_: bool = False) -> None:
    """--log-level and --log-json, on `nprt` itself and on `nprt serve` (whose level, when
    given, wins; absent, it leaves the global one alone)."""
    unset = None if global_ else argparse.SUPPRESS
    level_help = ("console log level (default: WARNING, INFO with -v or for serve)" if global_
                  else "console log level (default: INFO)")
    p.add_argument("--log-level", type=str.upper, choices=LEVELS, default=unset,
                   help=level_help)
    p.add_argument("--log-json", action="store_true", default=False if global_ else unset,
                   help="log one JSON object per line instead of text")
