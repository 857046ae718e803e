"""The Ray settings that cut Ray's CPU per parcel (workers/runtime/raysession.py, remote.py,
pool.py): applied where they can be, and never where Ray refuses them."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest
import ray
import yaml

from nprt.workers.runtime.protocol import Parcel, ShardConfig
from nprt.workers.runtime.raysession import RAY_SYSTEM_CONFIG, _starts_local
from nprt.workers.runtime.remote import ShardActor
from nprt.workers.settings import RenderSettings

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("address, env, starts", [
    ("local", None, True),
    (None, "local", True),
    ("10.0.0.1:6379", None, False),
    (None, "10.0.0.1:6379", False),
    ("local", "10.0.0.1:6379", True),  # "local" starts one whatever RAY_ADDRESS says
    ("auto", "10.0.0.1:6379", False),
])
def test_the_system_config_goes_only_to_a_ray_that_nprt_starts(monkeypatch, address, env,
                                                                 starts):
    """ray.init refuses a system config when it joins a running Ray."""
    if env is None:
        monkeypatch.delenv("RAY_ADDRESS", raising=False)
    else:
        monkeypatch.setenv("RAY_ADDRESS", env)
    assert _starts_local(address) is starts


def test_the_cluster_head_starts_ray_with_nprts_system_config():
    """A cluster's nodes take the head's system config; nprt cannot set it when it joins."""
    cluster = yaml.safe_load((REPO / "deploy" / "cluster.yaml").read_text())
    head = [c for c in cluster["head_start_ray_commands"] if "ray start" in c]
    assert len(head) == 1
    argv = shlex.split(head[0])
    config = next(a.split("=", 1)[1] for a in argv if a.startswith("--system-config="))
    assert yaml.safe_load(config) == RAY_SYSTEM_CONFIG


def test_the_shaped_test_cluster_starts_ray_with_nprts_system_config():
    """deploy/netcluster.sh (bench_network's two shaped nodes) starts its head with the
    same config, so its renders pay what a local or `ray up` render pays per parcel."""
    script = (REPO / "deploy" / "netcluster.sh").read_text()
    configs = [line.split("--system-config=", 1)[1].split()[0] for line in script.splitlines()
               if "--system-config=" in line]
    assert len(configs) == 1
    assert yaml.safe_load(shlex.split(configs[0])[0]) == RAY_SYSTEM_CONFIG


def test_a_delivery_makes_no_object_ref_and_still_arrives(ray_local):
    """Nobody reads a delivery's answer, so `deliver` returns none. The parcel still
    reaches the wavefront thread: on an actor with no shard loaded, its step fails, and
    the next poll says so."""
    actor = ray.remote(ShardActor).options(num_cpus=0, enable_task_events=False).remote(
        ShardConfig(0, 1, RenderSettings()))
    try:
        assert actor.deliver.remote(Parcel(None, {})) is None  # epoch None: no run begun
        with pytest.raises(ray.exceptions.RayTaskError, match="failed in its wavefront"):
            ray.get(actor.poll.remote(None, 60.0))
    finally:
        ray.kill(actor)


def test_the_system_config_survives_a_ray_started_with_it():
    """ray.init adds its own entries (object spilling, with its session's directory) to the
    dict it is given: nprt's config is read-only and every start passes a copy, so a later
    start (and the comparisons above) see nprt's settings only."""
    with pytest.raises(TypeError):
        RAY_SYSTEM_CONFIG["max_direct_call_object_size"] = 1  # type: ignore[index]
    assert dict(RAY_SYSTEM_CONFIG) == {"max_direct_call_object_size": 1 << 20}
