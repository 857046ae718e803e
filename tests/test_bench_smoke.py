"""Every benchmark runs: each bench/<group>/*.py entry point (a module with a `__main__`
block) runs once with `--smoke`, its smallest input, in a subprocess. Results go to a
temporary folder (NPRT_BENCH_RESULTS), scenes and proxies to empty caches, as on a fresh
checkout. Not timed. The selected runs go PARALLEL at a time in one fixture; each script's
exit status is its own test, and no README or recorded result may change. SLOW ones (a
multi-process runtime at scale, minutes even at their smallest) are marked slow.

The runs join one local Ray (RAY_ADDRESS; bench.common.start_ray and the pools connect to
it) that a holder process keeps up while they run: starting a Ray took 9 s of each run
under load."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path

import pytest

from bench.common import child_env

REPO = Path(__file__).resolve().parents[1]
BENCH = REPO / "bench"
GROUPS = ("render", "proxy", "training", "experiments", "network", "service")
PARALLEL = 2  # CI has two cores; more runs at once only share them
RUN_TIMEOUT_S = 600  # a hung bench fails instead of stalling CI
# bench_massive: four driver processes and two training rounds;
# bench_scale: four pools and a job manager.
SLOW = ("bench.render.bench_massive", "bench.render.bench_scale")
# Started first, so that no long run is left alone at the end: the longest walls of a serial
# `pytest tests/test_bench_smoke.py` (2 at a time, 2026-11-26 23:50, load 1.5 -> 13): 82, 42,
# 37 and 36 s; the other 27 runs took 28 s or less.
LONG_FIRST = ("bench.render.bench_massive", "bench.service.bench_render_effect",
              "bench.render.bench_scale", "bench.render.bench_strong_scaling")
# Logical CPUs of the shared Ray: two runs at a time, each with a K = 2 pool and its
# training tasks, never wait for CPUs the other holds.
SHARED_RAY_CPUS = 8
# A new local Ray turns token authentication on by itself (the token in ~/.ray/auth_token);
# a driver that joins it must be told to send that token.
SHARED_AUTH = {"RAY_AUTH_MODE": "token"}
# Started with RAY_ADDRESS=local; prints its address and holds Ray until stdin closes.
_HOLDER = """
import logging, sys
import ray
ray.init(num_cpus=int(sys.argv[1]), include_dashboard=False, log_to_driver=False,
         logging_level=logging.ERROR)
print(ray.get_runtime_context().gcs_address, flush=True)
sys.stdin.read()
ray.shutdown()
"""

pytestmark = pytest.mark.timeout(3600)  # the fixture runs every selected bench


def entry_points() -> list[str]:
    """Dotted module names of every bench script with a `__main__` block."""
    return sorted(f"bench.{p.parent.name}.{p.stem}" for p in BENCH.glob("*/*.py")
                  if 'if __name__ == "__main__":' in p.read_text())


def _fingerprint() -> dict[str, str]:
    """sha256 of both READMEs and of every file in bench/results."""
    files = [BENCH / "README.md", REPO / "README.md", *sorted((BENCH / "results").glob("*"))]
    return {str(f.relative_to(REPO)): hashlib.sha256(f.read_bytes()).hexdigest()
            for f in files if f.is_file()}


def _run(module: str, out: Path, caches: Path, ray_address: str
         ) -> tuple[subprocess.CompletedProcess, float]:
    env = child_env(NPRT_BENCH_RESULTS=str(out), RAY_ADDRESS=ray_address, **SHARED_AUTH,
                    NPRT_SCENE_CACHE=str(caches / "scenes"),
                    NPRT_PROXY_CACHE=str(caches / "proxies"), MPLBACKEND="Agg")
    t0 = time.perf_counter()
    try:
        res = subprocess.run([sys.executable, "-m", module, "--smoke"], cwd=REPO, env=env,
                             capture_output=True, text=True, timeout=RUN_TIMEOUT_S)
    except subprocess.TimeoutExpired as e:
        res = subprocess.CompletedProcess(e.cmd, -9, str(e.stdout or ""),
                                          f"{e.stderr or ''}\ntimed out after {e.timeout} s")
    return res, time.perf_counter() - t0


@contextmanager
def _shared_ray():
    """The address of a local Ray held up by a child process until the block ends."""
    env = {**os.environ, "RAY_ADDRESS": "local", **SHARED_AUTH}
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, str(SHARED_RAY_CPUS)], env=env,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    try:
        address = holder.stdout.readline().strip()
        if not address:
            raise RuntimeError(f"the shared Ray did not start: {holder.stderr.read()[-3000:]}")
        yield address
    finally:
        holder.stdin.close()  # the holder shuts Ray down and exits
        try:
            holder.wait(timeout=120)
        except subprocess.TimeoutExpired:
            holder.kill()
            holder.wait()


@pytest.fixture(scope="module")
def smoke_runs(request, tmp_path_factory):
    """{module: CompletedProcess} of every selected entry point, and the fingerprints
    before and after all of them."""
    before = _fingerprint()
    root = tmp_path_factory.mktemp("bench-smoke")
    mods = [item.callspec.params["module"] for item in request.session.items
            if item.originalname == "test_bench_runs_on_its_smallest_input"]
    mods.sort(key=lambda m: LONG_FIRST.index(m) if m in LONG_FIRST else len(LONG_FIRST))
    with _shared_ray() as address, ThreadPoolExecutor(PARALLEL) as pool:
        done = list(pool.map(lambda m: _run(m, root / m, root / "caches", address), mods))
    # wall seconds per run, for whoever sizes the CI budget (reported, never asserted)
    report = request.config.pluginmanager.get_plugin("terminalreporter")
    capture = request.config.pluginmanager.get_plugin("capturemanager")
    if report is not None and capture is not None:
        with capture.global_and_fixture_disabled():
            report.write_line(f"\nbench smoke runs, {PARALLEL} at a time, wall s (load "
                              f"{os.getloadavg()[0]:.1f}):")
            for m, (_, wall) in sorted(zip(mods, done, strict=True), key=lambda x: -x[1][1]):
                report.write_line(f"  {wall:7.1f}  {m}")
    runs = {m: res for m, (res, _) in zip(mods, done, strict=True)}
    return runs, before, _fingerprint()


def test_every_bench_group_has_entry_points():
    assert {m.split(".")[1] for m in entry_points()} >= set(GROUPS)


@pytest.mark.parametrize("module", [
    pytest.param(m, marks=pytest.mark.slow) if m in SLOW else m for m in entry_points()])
def test_bench_runs_on_its_smallest_input(smoke_runs, module):
    res = smoke_runs[0][module]
    assert res.returncode == 0, f"{module} --smoke:\n{res.stdout[-2000:]}\n{res.stderr[-4000:]}"


def test_smoke_runs_change_no_readme_nor_recorded_result(smoke_runs):
    _, before, after = smoke_runs
    changed = sorted(k for k in before.keys() | after.keys() if before.get(k) != after.get(k))
    assert changed == []
