"""bench_network's scaling run end to end on a tiny scene: traced renders through the
coordinator and its pool registry, then the model and the report (with the recorded
bandwidth table beside it). Guards the benchmark against runtime API changes."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_scaling_traces_replay_and_report(tmp_path):
    shutil.copy(REPO / "bench" / "results" / "network_bandwidth.json", tmp_path)
    cmd = [sys.executable, "-m", "bench.network.bench_network", "scaling", "--size", "tiny",
           "--scenes", "sculpture", "--ks", "2,3", "--width", "32", "--spp", "1",
           "--bounces", "2", "--no-readme", "--out", str(tmp_path)]
    env = {**os.environ, "RAY_ADDRESS": "local", "PYTHONPATH": str(REPO)}
    res = subprocess.run(cmd, env=env, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    runs = json.loads((tmp_path / "network_scaling.json").read_text())["runs"]
    assert sorted((r["mode"], r["k"]) for r in runs) == [
        ("exact", 2), ("exact", 3), ("proxy", 2), ("proxy", 3)]
    for r in runs:
        shards = {c["shard"] for c in r["trace"]["calls"]}
        assert shards == set(range(r["k"])) and len(r["cpu_s"]) == r["k"]
    summary = json.loads((tmp_path / "network_summary.json").read_text())
    assert {row["k"] for row in summary["scaling"]} == {2, 3}
    assert (tmp_path / "network_scaling.png").stat().st_size > 0
