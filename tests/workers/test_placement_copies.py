"""Placement in proxy mode: meshes the proxy plan copies to every shard (a proxy heavier
than its mesh) are taken out of the work partition, which is then made again, so that no
shard is left with nothing of its own. forest:small copies every tree but the pine: before,
at K = 8 five shards owned no instance and sat idle."""

from __future__ import annotations

import numpy as np
import pytest

from nprt.scene.store import open_scene
from nprt.workers.runtime.placement import plan_placement
from nprt.workers.runtime.protocol import EVERYWHERE
from nprt.workers.settings import RenderSettings


@pytest.fixture(scope="module")
def forest_small():
    return open_scene("forest:small")


@pytest.mark.parametrize("k", [2, 4, 8])
@pytest.mark.parametrize("mode", ["proxy", "oracle"])
def test_every_shard_owns_instances_of_its_own(forest_small, k, mode):
    placed = plan_placement(forest_small, RenderSettings(width=16, height=12, shards=k,
                                                         mode=mode))
    copied = placed.plan.replicated
    assert copied, "forest:small copies meshes in proxy mode: the case is exercised"
    owned = np.bincount(placed.owner[placed.owner != EVERYWHERE], minlength=k)
    assert owned.min() >= 1, f"shards without an instance of their own: {owned.tolist()}"
    # The copied meshes are on every shard and owned by none; the partition left them out.
    for m in copied:
        assert all(m in held for held in placed.shard_meshes)
        assert np.all(placed.owner[forest_small.instances_of_mesh(m)] == EVERYWHERE)
        d = placed.plan.decision(m)
        assert d.decision == "replicate" and "replicated exactly" in d.reason, d


def test_exact_mode_places_as_before(forest_small):
    """Exact mode has no plan: one partition, light meshes (the ground) copied."""
    placed = plan_placement(forest_small, RenderSettings(width=16, height=12, shards=4))
    assert placed.plan is None and placed.proxies == {}
    assert np.bincount(placed.owner[placed.owner != EVERYWHERE], minlength=4).min() >= 1


def test_a_scene_in_memory_trains_its_missing_proxies_here(tmp_path):
    """With no trainer (in-process shards: benchmarks, tests), the plan trains the proxies
    the cache lacks from the Scene's own meshes. It was handed the scene's metadata, which
    has no vertices, so every training failed and every mesh was traced exactly."""
    from nprt.scene.demos.family import build
    from nprt.workers.settings import ProxySettings

    scene = build("tiny")
    s = RenderSettings(width=16, height=12, shards=2, mode="proxy",
                       proxy=ProxySettings(width=16, steps=20))
    placed = plan_placement(scene, s, proxy_dir=tmp_path)
    failed = [d.reason for d in placed.plan.decisions if "failed" in d.reason]
    assert failed == []
    assert placed.proxies, [(d.name, d.decision, d.reason) for d in placed.plan.decisions]
