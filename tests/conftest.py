"""Test order for parallel runs (`pytest -n 2 --dist loadfile --no-loadscope-reorder`, the
README's command): xdist hands out whole files in collection order, so the longest files go
first and the short ones fill the gaps at the end. A plain serial run keeps pytest's order.
Before a parallel run on a cold numba cache (a fresh checkout), one process compiles the
kernels first (tests/warm_kernels.py), so the workers' processes load them instead."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

LONGEST = "tests/test_bench_smoke.py"  # every bench entry point, minutes on two cores


def _weight(path: str, slow_files: set[str]) -> int:
    return 0 if path == LONGEST else 1 if path in slow_files else 2


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    if not hasattr(config, "workerinput"):  # not an xdist worker
        return
    slow_files = {item.nodeid.split("::")[0] for item in items
                  if item.get_closest_marker("slow") is not None}
    items.sort(key=lambda item: _weight(item.nodeid.split("::")[0], slow_files))


@pytest.hookimpl(optionalhook=True)  # an xdist hook: unknown to pytest without it
def pytest_xdist_setupnodes(config, specs):
    """Before xdist starts its workers: compile the kernels here if numba's cache is cold."""
    from nprt.workers.jitcache import cold_kernel_modules  # reads files: imports no numba

    if not cold_kernel_modules():
        return
    done = subprocess.run([sys.executable, "-m", "tests.warm_kernels"], cwd=REPO, text=True,
                          capture_output=True, timeout=900)
    line = (done.stdout.strip().splitlines() or [""])[-1] if done.returncode == 0 else (
        f"warm_kernels failed (rc {done.returncode}), the tests compile what they run: "
        f"{done.stderr[-1500:]}")
    report = config.pluginmanager.get_plugin("terminalreporter")
    if report is not None:
        report.write_line(line)
