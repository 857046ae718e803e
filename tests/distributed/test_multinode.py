"""Three Ray nodes, one shard pinned to each: rays move node to node through the object
store and the image is still the reference. Shuts the shared local Ray down for its own
cluster; `ray_local` restarts it for later modules."""

from __future__ import annotations

import os
import shutil
import tempfile
import threading

import pytest
import ray
from ray.cluster_utils import Cluster

from nprt.workers.render import render
from nprt.workers.runtime.coordinator import Coordinator
from nprt.workers.wavefront.batch import KIND_NAMES
from tests.distributed.helpers import assert_matches, settings

NODES = 3
OBJECT_STORE_BYTES = 128 * 1024**2  # per node; the test moves a few MB at most


@pytest.fixture(scope="module")
def cluster(_ray_session):
    # A service job thread left running by an earlier test could shut Ray down under
    # this fixture (seen once in CI as ray.init failing half-way); name it if so.
    leftover = [t.name for t in threading.enumerate() if t.name.startswith("nprt-")]
    assert not leftover, f"threads of an earlier service still running: {leftover}"
    if ray.is_initialized():
        ray.shutdown()
    # Cluster writes its address to <Ray's temp dir>/ray_current_cluster, where any
    # ray.init() without an address on this host (another pytest-xdist worker's fixture)
    # would join it: a private temp dir (short: socket paths) keeps it to this module.
    previous, tmp = os.environ.get("RAY_TMPDIR"), tempfile.mkdtemp(prefix="nprt-mn-")
    os.environ["RAY_TMPDIR"] = tmp
    c = None
    try:  # the cluster's processes go even when joining it fails
        c = Cluster(initialize_head=True, head_node_args=dict(
            num_cpus=1, resources={"node0": 1}, object_store_memory=OBJECT_STORE_BYTES,
            include_dashboard=False))
        for i in range(1, NODES):
            c.add_node(num_cpus=1, resources={f"node{i}": 1},
                       object_store_memory=OBJECT_STORE_BYTES)
        c.wait_for_nodes()
        ray.init(address=c.address, log_to_driver=False, include_dashboard=False)
        yield c
    finally:
        ray.shutdown()
        if c is not None:
            c.shutdown()
        if previous is None:
            os.environ.pop("RAY_TMPDIR", None)
        else:
            os.environ["RAY_TMPDIR"] = previous
        shutil.rmtree(tmp, ignore_errors=True)


def _node_of(actor) -> str:
    return ray.get(actor.__ray_call__.remote(
        lambda self: ray.get_runtime_context().get_node_id()))


@pytest.mark.slow
def test_shards_pinned_to_three_nodes_match_reference(cluster, scenes, references, tmp_path):
    scene = scenes["sculpture"]
    pins = [{"resources": {f"node{i}": 0.01}} for i in range(NODES)]
    coord = Coordinator(scene, settings(NODES), shard_options=pins)
    try:
        nodes = [_node_of(a) for a in coord.actors]
        result = render(scene, coord.s, renderer=coord)
    finally:
        coord.close()

    # Each shard runs on the node that carries its pin, so all three nodes differ.
    resources_of = {n["NodeID"]: n["Resources"] for n in ray.nodes() if n["Alive"]}
    assert len(resources_of) == NODES
    for i, node in enumerate(nodes):
        assert f"node{i}" in resources_of[node], (i, node, resources_of[node])
    assert len(set(nodes)) == NODES, nodes
    assert len({i["pid"] for i in coord.shard_info}) == NODES

    assert_matches(tmp_path, "sculpture_3_nodes", result.film.image(),
                   references["sculpture"].film.image())
    st = result.stats.to_dict()
    assert st["total_bytes"] > 0, st
    for kind in KIND_NAMES:  # every kind of ray crossed between nodes
        assert st["transfers"][kind] > 0 and st["bytes"][kind] > 0, (kind, st)
