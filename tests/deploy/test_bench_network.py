"""bench_network's scaling run end to end on a tiny scene: traced renders through the
coordinator and its pool registry, then the model and the report (with the recorded
bandwidth table beside it). Guards the benchmark against runtime API changes, and the
report against results recorded with the earlier runtime's call trace."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def _report(out: Path) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "bench.network.bench_network", "report", "--no-readme",
           "--out", str(out)]
    env = {**os.environ, "PYTHONPATH": str(REPO), "MPLBACKEND": "Agg"}
    return subprocess.run(cmd, env=env, cwd=REPO, capture_output=True, text=True, timeout=600)


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
        steps = r["trace"]["steps"]
        # a shard whose boxes no ray of this tiny image reaches runs no step
        assert steps and {s["shard"] for s in steps} <= set(range(r["k"]))
        assert len(r["cpu_s"]) == len(r["shard_stats"]) == r["k"]
        # every pass admitted was run by some step, and the shards' totals count the steps
        assert set(r["trace"]["admitted"]) <= {p for s in steps for p in s["passes"]}
        assert sum(sh["steps"] for sh in r["shard_stats"]) == len(steps)
        assert r["coordinator_cpu_s"] > 0
    summary = json.loads((tmp_path / "network_summary.json").read_text())
    assert {row["k"] for row in summary["scaling"]} == {2, 3}
    assert all(row["1 Gbit/s"] > 0 for row in summary["scaling"])
    assert (tmp_path / "network_scaling.png").stat().st_size > 0


def test_report_leaves_the_model_out_for_call_traces(tmp_path):
    """Results of the earlier runtime ({"k", "calls"} traces) still make their tables."""
    res = json.loads((REPO / "bench" / "results" / "network_bandwidth.json").read_text())
    for r in res["runs"]:
        r["trace"] = {"k": r["trace"]["k"], "calls": []}
    (tmp_path / "network_bandwidth.json").write_text(json.dumps(res))
    done = _report(tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "Model: not run" in done.stdout and "| n/a |" in done.stdout
    summary = json.loads((tmp_path / "network_summary.json").read_text())
    assert summary["validation"] is None
    assert all("model_b_star_bps" not in v for v in summary["share"].values())
