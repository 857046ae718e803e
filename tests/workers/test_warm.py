"""A shard's warm-up compiles (or loads from numba's cache) every kernel its renders run,
the proxy queries included: a 4x4 corner tile may ask no proxy at all, and a job's first
proxy query then compiled them inside its render (20 s of CPU on a fresh cache). Run in a
fresh interpreter, whose dispatchers have compiled nothing yet."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

_PROBE = """
import json
from nprt.scene.demos import make_demo
from nprt.workers.routing import proxy_pairs
from nprt.workers.settings import RenderSettings
from nprt.workers.wavefront.inprocess import shards_in_process

s = RenderSettings(width=64, height=48, spp=1, mode="proxy", shards=2)
shards = shards_in_process(make_demo("forest", "small"), s, warm=False)
def compiled():
    return sum(len(f.signatures) for f in (proxy_pairs.walk_queries, proxy_pairs.decide))
before = compiled()
modeled = [len(sh.policy.modeled) for sh in shards]
for sh in shards:
    sh.warm()
print(json.dumps({"before": before, "after": compiled(), "modeled": modeled}))
"""


def test_warm_up_compiles_the_proxy_query_kernels():
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    out = subprocess.run([sys.executable, "-c", _PROBE], cwd=REPO, env=env, text=True,
                         capture_output=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert max(got["modeled"]) > 0, got  # some shard answers boxes by proxy
    assert got["before"] == 0 and got["after"] >= 2, got
