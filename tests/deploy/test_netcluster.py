"""deploy/netcluster.sh for real, on one three-node cluster for the module (bringing one up
takes seconds): Ray nodes in network namespaces with shaped links, a render whose shards ran
on two different nodes; then a node whose raylet is killed in the middle of a render; last,
nothing left behind after `down`. Skipped where namespaces are not allowed (the script says
why). Renders run as child processes: Ray reads its token mode at import.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.deploy.netcluster import NetCluster
from tests.distributed.helpers import assert_matches

REPO = Path(__file__).resolve().parents[2]
# Far beyond what these renders take; only there to turn a hang into a failure.
HANG_GUARD_S = 900


def _env() -> dict:
    return {**os.environ, "RAY_AUTH_MODE": "token", "PYTHONPATH": str(REPO)}


@pytest.fixture(scope="module")
def cluster():
    """Three nodes: two shards spread over two of them, and a spare for the shard of a
    killed node. The last test takes it down; this only cleans up after a failure."""
    c = NetCluster(3, "nprtt", "10.214.0", 26479)
    c.up("1gbit")
    yield c
    if c.state.exists():
        c.down()


@pytest.mark.slow
@pytest.mark.timeout(2 * HANG_GUARD_S)
def test_up_render_spreads_shards_on_two_nodes(cluster, tmp_path):
    assert cluster.address == "10.214.0.1:26479"
    status = cluster.run("status", *cluster.opts).stdout
    assert "links 1gbit" in status, status
    stats = tmp_path / "stats.json"
    cmd = [sys.executable, "-m", "nprt.service.cli", "render", "sculpture", "--size", "small",
           "--width", "32", "--height", "24", "--spp", "1", "--bounces", "2",
           "--shards", "2", "--ray-address", cluster.address, "-o", str(tmp_path / "out.png"),
           "--stats", str(stats)]
    res = subprocess.run(cmd, env=_env(), capture_output=True, text=True,
                         timeout=HANG_GUARD_S, cwd=REPO)
    assert res.returncode == 0, res.stderr[-3000:]
    st = json.loads(stats.read_text())
    nodes = [s["node"] for s in st["shard_stats"]]
    assert len(set(nodes)) == 2, st["shard_stats"]
    assert set(nodes) <= {cluster.node_ip(i) for i in range(cluster.nodes)}, nodes
    assert st["total_bytes"] > 0  # rays crossed between the two nodes


# The driver speaks on its own pipe (fd argv[4]): Ray forwards worker and raylet logs to the
# driver's stdout, and a raylet's death notice can land in the middle of a line there.
_FAILURE_DRIVER = """
import json, os, sys
import numpy as np
from nprt.scene.demos import make_demo
from nprt.workers.render import render
from nprt.workers.settings import RenderSettings

scene = make_demo("sculpture", "small")
s = RenderSettings.model_validate_json(sys.argv[2])
channel = os.fdopen(int(sys.argv[4]), "w")
def say(msg):
    print(json.dumps(msg), file=channel, flush=True)
def on_pass(done):
    say({"pass": done.progress.count, "of": done.total})
try:
    res = render(scene, s, on_pass=on_pass, ray_address=sys.argv[1])
except Exception as e:
    say({"error": f"{type(e).__name__}: {e}"})
    sys.exit(3)
np.save(sys.argv[3], res.film.image())
say({"done": True})
"""


@pytest.mark.slow
@pytest.mark.timeout(2 * HANG_GUARD_S)
def test_killing_a_node_mid_render_gives_the_same_image_or_a_clear_error(cluster, tmp_path):
    """Three nodes, two shards: the shard of the killed node may restart on the spare one.
    The render must end (same image as the single-process reference, or a clear error)."""
    from nprt.scene.demos import make_demo
    from nprt.workers.settings import RenderSettings
    from tests.distributed.helpers import reference

    s = RenderSettings(width=48, height=32, spp=4, spp_per_pass=1, tile_size=16, bounces=3,
                       shards=2, seed=5)
    address = cluster.address
    out, err = tmp_path / "image.npy", tmp_path / "driver.err"
    read_fd, write_fd = os.pipe()
    with err.open("w") as err_file:  # a file: a full output pipe would block the driver
        driver = subprocess.Popen(
            [sys.executable, "-c", _FAILURE_DRIVER, address, s.model_dump_json(), str(out),
             str(write_fd)],
            env=_env(), stdout=err_file, stderr=err_file, pass_fds=(write_fd,), cwd=REPO)
    os.close(write_fd)  # the child holds the only write end: EOF when it exits
    try:
        killed, lines = None, []
        with os.fdopen(read_fd) as channel:
            for line in channel:  # the timeout marker ends a render that hangs
                lines.append(line)
                msg = json.loads(line)
                if killed is None and msg.get("pass", 0) >= 3:
                    killed = _kill_a_shard_node(cluster)
        rc = driver.wait(timeout=HANG_GUARD_S)
    finally:
        if driver.poll() is None:
            driver.kill()
    assert killed is not None, f"the render ended before a node could be killed: {lines}"
    last = json.loads(lines[-1])
    print(f"node {killed} killed after pass 3; the driver ended with {rc}: {last}")
    if rc == 0:
        assert last == {"done": True}
        ref = reference(make_demo("sculpture", "small"), s).film.image()
        assert_matches(tmp_path, "node_killed", np.load(out), ref)
    else:  # a failure must say what happened, in one line
        assert rc == 3 and "error" in last, (rc, lines[-3:], err.read_text()[-2000:])
        assert any(w in last["error"].lower() for w in ("node", "shard", "lost", "died")), last


def _kill_a_shard_node(cluster: NetCluster) -> int:
    """SIGKILL the raylet of a node that runs a shard (a node whose namespace holds a
    `ray::Shard` worker). Returns the node's index."""
    for i in range(cluster.nodes):
        ns = f"{cluster.name}-ns{i}"
        pids = subprocess.run(["ip", "netns", "pids", ns], capture_output=True,
                              text=True).stdout.split()
        comms = [Path(f"/proc/{p}/comm").read_text().strip() for p in pids
                 if Path(f"/proc/{p}/comm").exists()]
        if any(c.startswith("ray::Shard") for c in comms):
            os.kill(cluster.raylet_pid(i), signal.SIGKILL)
            return i
    raise AssertionError("no node runs a shard")


@pytest.mark.slow
@pytest.mark.timeout(HANG_GUARD_S)
def test_down_leaves_nothing(cluster):
    """Last: after a killed node, too, `down` removes every namespace, link, cgroup, state
    file and Ray process of the cluster."""
    said = cluster.down()
    assert "nothing of cluster nprtt left" in said, said
    assert cluster.leftovers() == []
