"""Test order for parallel runs (`pytest -n 2 --dist loadfile --no-loadscope-reorder`, the
README's command): xdist hands out whole files in collection order, so the longest files go
first and the short ones fill the gaps at the end. A plain serial run keeps pytest's order."""

from __future__ import annotations

import pytest

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
