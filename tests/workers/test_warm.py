"""A shard's warm-up compiles (or loads from numba's cache) every kernel its renders run:
its 4x4 corner tile may hit nothing (no shadow ray) or ask no proxy, and the first timed
pass then compiled the occlusion walk or the proxy queries (20 s of CPU for a first proxy
render on a fresh cache). Checked in a fresh interpreter, whose dispatchers have compiled
nothing yet, on a scene whose corner tile reaches neither."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

_PROBE = """
import json, sys
from nprt.scene.demos import make_demo
from nprt.workers.kernels import crossings
from nprt.workers.routing import net_rows, proxy_pairs
from nprt.workers.settings import ProxySettings, RenderSettings
from nprt.workers.wavefront.inprocess import shards_in_process

mode, k = sys.argv[1], int(sys.argv[2])
kernels = {"occluded_walk": crossings.occluded_walk, "walk_queries": proxy_pairs.walk_queries,
           "decide": proxy_pairs.decide_queries, "net_inputs": net_rows.net_inputs,
           "deep_inputs": net_rows.deep_inputs, "net_answers": net_rows.net_answers}
# An accuracy target forest:small's tree proxies meet: at the default the plan copies the
# trees to every shard, and no shard would model anything.
s = RenderSettings(width=64, height=48, spp=1, mode=mode, shards=k,
                   proxy=ProxySettings(accuracy_target=0.9))
shards = shards_in_process(make_demo("forest", "small"), s, warm=False)
before = {n: len(f.signatures) for n, f in kernels.items()}
for sh in shards:
    sh.warm()
print(json.dumps({"before": before, "after": {n: len(f.signatures) for n, f in kernels.items()},
                  "modeled": [len(getattr(sh.policy, "modeled", ())) for sh in shards]}))
"""


def _probe(mode: str, k: int) -> dict:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    out = subprocess.run([sys.executable, "-c", _PROBE, mode, str(k)], cwd=REPO, env=env,
                         text=True, capture_output=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("k", [1, 2])
def test_warm_up_compiles_the_occlusion_walk(k):
    got = _probe("exact", k)
    assert got["before"]["occluded_walk"] == 0 and got["after"]["occluded_walk"] >= 1, got


def test_warm_up_compiles_the_proxy_query_kernels():
    got = _probe("proxy", 2)
    assert max(got["modeled"]) > 0, got  # some shard answers boxes by proxy
    names = ("walk_queries", "decide", "net_inputs", "deep_inputs", "net_answers")
    assert all(got["before"][n] == 0 for n in names), got
    assert all(got["after"][n] >= 1 for n in names), got
