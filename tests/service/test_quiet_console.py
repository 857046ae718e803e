"""A first run through Ray prints nothing of Ray's own: no Python log record of Ray's
(such as its token-authentication notice) and no line of its C++ core (core_worker.cc and
the like) reaches the console of `nprt render` unless --log-level debug."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
# "[2026-11-26 06:22:40,272 E 5712 5712] core_worker.cc:2465: ..." (C++, any severity;
# written straight to fd 2, so it may land in the middle of a progress bar's line)
RAY_CPP = re.compile(r"\[\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d+ [DIWEF] \d+ \d+\] \S+\.(cc|h):\d+")
# "2026-11-26 06:24:01,447\tWARNING authentication_token_setup.py:85 -- ..." (Ray's Python
# logger), and "(raylet)" / "(ShardActor pid=...)" forwarded from Ray's processes
RAY_PY = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d+\t[A-Z]+ \S+\.py:\d+ -- ")
RAY_FORWARDED = re.compile(r"^\((raylet|gcs_server|\w+ pid=\d+)")


def ray_lines(text: str) -> list[str]:
    """The console lines (split at newlines and a progress bar's carriage returns) that
    came from Ray."""
    return [ln for ln in text.splitlines()
            if RAY_CPP.search(ln) or RAY_PY.match(ln) or RAY_FORWARDED.match(ln)]


def test_ray_line_patterns_match_what_ray_prints():
    seen = ("[2026-11-26 06:22:40,272 E 5712 5712] core_worker.cc:2465: Actor with class "
            "name: 'ShardActor' has constructor arguments in the object store\n"
            "2026-11-26 06:24:01,447\tWARNING authentication_token_setup.py:85 -- Token "
            "authentication is enabled for this Ray cluster.\n"
            "(ShardActor pid=7218) warm-up done\n"
            "\rrender:   0%|          | 0.00/192 [00:00<?, ?path/s][2026-11-26 06:28:22,508 "
            "E 18856 18856] core_worker.cc:2465: Actor with class name: 'ShardActor'\n"
            "2026-11-26 06:20:54,311 WARNING nprt.workers.jitcache: compiling the numba kernels\n"
            "wrote out.png (16x12, 1 spp) in 4.2 s")
    assert len(ray_lines(seen)) == 4


@pytest.mark.slow
def test_a_distributed_render_prints_no_line_of_ray(tmp_path):
    env = {**os.environ, "RAY_ADDRESS": "local", "NPRT_SCENE_CACHE": str(tmp_path / "scenes"),
           "PYTHONPATH": str(REPO)}
    cmd = [sys.executable, "-m", "nprt.service.cli", "render", "forest:tiny", "--shards", "2",
           "--width", "16", "--height", "12", "--spp", "1", "-o", str(tmp_path / "out.png")]
    res = subprocess.run(cmd, env=env, cwd=tmp_path, capture_output=True, text=True,
                         timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert (tmp_path / "out.png").stat().st_size > 0
    assert ray_lines(res.stdout + res.stderr) == []


_LIBRARY_RENDER = """
from nprt.scene.demos import make_demo
from nprt.workers.render import render
from nprt.workers.settings import RenderSettings
r = render(make_demo("forest", "tiny"), RenderSettings(width=16, height=12, spp=1, shards=2))
print(float(r.film.image().mean()))
"""


def test_a_library_render_of_a_scene_in_memory_prints_no_line_of_ray(tmp_path):
    """An in-memory scene's meshes go through Ray's object store; they reach a shard as an
    argument of `load`, not of its constructor (Ray printed an error line for that)."""
    env = {**os.environ, "RAY_ADDRESS": "local", "PYTHONPATH": str(REPO)}
    res = subprocess.run([sys.executable, "-c", _LIBRARY_RENDER], env=env, cwd=tmp_path,
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert float(res.stdout.strip().splitlines()[-1]) > 0
    assert ray_lines(res.stdout + res.stderr) == []
