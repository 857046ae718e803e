"""The driver imports none of the libraries that trace, checked at run time: the pool starts
shards through `nprt.workers.runtime.remote`, whose forwarder must cover every call the Shard
answers, and builds the instance table (numba's BVH) in a Ray task. Checked in a fresh
driver process, since this test process has imported everything already. The fast static
twin, which reads module-level imports, is tests/test_driver_contract.py."""

from __future__ import annotations

import inspect
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from nprt.scene.store import open_scene
from nprt.workers.runtime.remote import ShardActor
from nprt.workers.wavefront.shard import Shard
from tests.driver_contract import TRACING_LIBRARIES

REPO = Path(__file__).resolve().parents[2]


def _public(cls) -> set[str]:
    return {n for n, f in inspect.getmembers(cls, inspect.isfunction) if not n.startswith("_")}


def test_the_actor_answers_every_call_the_driver_and_peers_make():
    """Every `handle.method.remote(...)` in the runtime names a method of ShardActor, and
    every Shard method the actor forwards to exists."""
    runtime = REPO / "workers" / "runtime"
    called = set()
    for name in ("coordinator.py", "pool.py", "remote.py"):
        called |= set(re.findall(r"\.(\w+)\.remote\(", (runtime / name).read_text()))
    called.discard("build_world")
    assert called and called <= _public(ShardActor), called - _public(ShardActor)
    forwarded = set(re.findall(r"self\._shard\.(\w+)\(", (runtime / "remote.py").read_text()))
    assert forwarded and forwarded <= _public(Shard), forwarded - _public(Shard)


_DRIVER = """
import json, sys
from nprt.scene.store import open_scene
from nprt.workers.frames import render_frames
from nprt.workers.settings import RenderSettings

meta = open_scene("windy:tiny")  # animated: a later frame rebuilds the instance table
out = {}
for mode in ("exact", "proxy"):
    s = RenderSettings(width=24, height=16, spp=1, bounces=2, shards=2, mode=mode)
    done = list(render_frames(meta, s, range(2)))
    out[mode] = [float(d.result.film.image().mean()) for d in done]
out["loaded"] = sorted({m.split(".")[0] for m in sys.modules} & set(sys.argv[1].split(",")))
print(json.dumps(out))
"""


@pytest.mark.slow
def test_a_render_driver_imports_no_tracing_library(tmp_path, monkeypatch):
    monkeypatch.setenv("NPRT_SCENE_CACHE", str(tmp_path / "scenes"))
    open_scene("windy:tiny")  # generated here (trimesh), so the driver opens a stored scene
    env = {**os.environ, "RAY_ADDRESS": "local"}
    res = subprocess.run([sys.executable, "-c", _DRIVER, ",".join(TRACING_LIBRARIES)],
                         env=env, capture_output=True, text=True, cwd=REPO, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert min(out["exact"] + out["proxy"]) > 0  # every frame rendered something
    assert out["loaded"] == [], f"the driver imported {out['loaded']}"
