"""Model only what a scene requires: no proxy where every shard is local, exact replication
for meshes lighter than a proxy, and the narrowest width meeting the accuracy target."""

from __future__ import annotations

import json

import pytest

from nprt.proxies.cache import ProxyCache
from nprt.proxies.config import ProxyConfig
from nprt.proxies.policy import Z_LEAD, lead_z, plan_proxies
from nprt.scene.partition import partition
from tests.proxies.helpers import scene_of, sphere, stand_in_proxy, torus, triangle

QUICK = ProxyConfig(steps=1000, n_samples=1 << 17, grid=32,
                    eval_samples=1 << 14)


@pytest.fixture
def cache(tmp_path):
    return ProxyCache(tmp_path, shipped_dir=None)


def test_one_shard_needs_no_proxies(cache):
    scene = scene_of(sphere(), torus(), triangle())
    plan = plan_proxies(scene, partition(scene, 1), cache=cache, train=False)
    assert [d.decision for d in plan.decisions] == ["none"] * 3
    assert plan.proxies == {} and plan.replicated == set()
    assert "only shard" in plan.decisions[0].reason


def test_a_mesh_held_by_every_shard_needs_no_proxy(cache):
    scene = scene_of(torus(), copies=4)  # one mesh, more shards than meshes: it is split
    part = partition(scene, 2)
    assert all(0 in held for held in part.shard_meshes)
    plan = plan_proxies(scene, part, cache=cache, train=False)
    assert plan.decisions[0].decision == "none" and "all 2 shards" in plan.decisions[0].reason


def test_a_mesh_lighter_than_its_proxy_is_replicated(cache):
    scene = scene_of(triangle(), torus())
    plan = plan_proxies(scene, partition(scene, 2), cache=cache, train=False)
    tri, tor = plan.decisions
    assert tri.decision == "replicate" and plan.replicated == {0}
    assert tri.mesh_bytes < tri.proxy_bytes
    # Nothing cached and training off: the torus is traced exactly, and the plan says why.
    assert tor.decision == "fallback" and "training is disabled" in tor.reason
    json.dumps(plan.to_dict())


def test_a_mesh_no_width_models_well_enough_is_replicated_if_lighter_than_the_widest(cache):
    """Below the target at every width, an exact copy is the better buy when it costs less
    than the widest proxy the policy was ready to ship; a heavier mesh keeps its best proxy."""
    light, heavy = torus(), torus(128, 64)  # about 37 kB and 393 kB
    for m in (light, heavy):
        for w in (16, 64):  # stand-ins score 0.5 held-out accuracy
            cfg = ProxyConfig().with_width(w)
            cache.put(m, cfg, stand_in_proxy(m, cfg))
    scene = scene_of(light, heavy)
    plan = plan_proxies(scene, partition(scene, 2), cache=cache, train=False, widths=(16, 64))
    lt, hv = plan.decisions
    assert lt.decision == "replicate" and "lighter than the widest proxy" in lt.reason, lt
    assert hv.decision == "proxy" and "no width met" in hv.reason, hv
    assert plan.replicated == {0} and set(plan.proxies) == {1}


def _below_target(cache, mesh, accuracy: dict[int, float], eval_rays=65536):
    """Cache stand-ins of `mesh` scoring accuracy[width] over eval_rays held-out rays."""
    for w, a in accuracy.items():
        cfg = ProxyConfig().with_width(w)
        cache.put(mesh, cfg, stand_in_proxy(mesh, cfg, a, eval_rays))


def test_below_the_target_a_wider_proxy_must_lead_by_more_than_chance(cache):
    """No width meets the target: the narrowest is kept unless a wider one's held-out lead is
    beyond Z_LEAD standard errors. The accuracies are those the held-out foliage scene's
    leaf meshes got (first two) and forest's pine (last), over 65,536 held-out rays."""
    leafy, sparse, pine = torus(128, 64), torus(120, 64), torus(112, 64)
    _below_target(cache, leafy, {16: 0.9057, 32: 0.9074, 64: 0.9078})
    _below_target(cache, sparse, {16: 0.8912, 32: 0.8926, 64: 0.8947})
    _below_target(cache, pine, {16: 0.9462, 32: 0.9522, 64: 0.9552})
    scene = scene_of(leafy, sparse, pine)
    plan = plan_proxies(scene, partition(scene, 2), cache=cache, train=False)
    assert [d.decision for d in plan.decisions] == ["proxy"] * 3
    # 64 leads 16 by 1.3 SE: chance, so the cheaper net
    assert plan.decisions[0].width == 16 and "width 16 (0.9057) chosen" in plan.decisions[0].reason
    # 64 leads 16 by 2.05 SE, but 32 by 1.2: the narrowest within reach of the best
    assert plan.decisions[1].width == 32
    # pine: 64 leads 32 by 2.6 SE and 16 by 7.5: the lead is real, the wider net is kept
    assert plan.decisions[2].width == 64 and "chosen" not in plan.decisions[2].reason
    assert plan.decisions[0].tried == {16: 0.9057, 32: 0.9074, 64: 0.9078}


def test_a_lead_counts_in_standard_errors_of_the_held_out_rays(cache):
    m = torus()
    cfg = ProxyConfig()

    def proxy(a, n=None):
        return stand_in_proxy(m, cfg, a, n)

    assert lead_z(proxy(0.90, 10_000), proxy(0.90, 10_000)) == 0.0
    assert lead_z(proxy(0.89, 10_000), proxy(0.90, 10_000)) < 0
    # sqrt((0.91 * 0.09 + 0.9 * 0.1) / 10,000) = 0.0041: a lead of 0.01 is 2.4 of them
    assert lead_z(proxy(0.91, 10_000), proxy(0.90, 10_000)) == pytest.approx(
        0.01 / ((0.91 * 0.09 + 0.9 * 0.1) / 10_000) ** 0.5)
    # the same lead over 100x fewer rays is chance
    assert lead_z(proxy(0.91, 100), proxy(0.90, 100)) < Z_LEAD
    # without counts (older reports) any lead counts: the most accurate, as before
    assert lead_z(proxy(0.91), proxy(0.90)) == float("inf")


def test_an_easy_mesh_gets_the_narrowest_width(cache):
    pytest.importorskip("torch", reason="training needs PyTorch")
    scene = scene_of(sphere(), torus())
    plan = plan_proxies(scene, partition(scene, 2), target_accuracy=0.8, cache=cache,
                        config=QUICK, widths=(16, 32, 64))
    d = plan.decisions[0]
    assert d.decision == "proxy" and d.width == 16 and list(d.tried) == [16]
    assert d.accuracy >= 0.8 and d.proxy_bytes == plan.proxies[0].nbytes
    assert plan.proxies[0].meta["content_hash"] == scene.meshes[0].content_hash


def test_a_harder_target_needs_a_wider_proxy_and_the_narrowest_that_meets_it_wins(cache):
    pytest.importorskip("torch", reason="training needs PyTorch")
    m = torus(128, 64)  # heavy enough (393 kB) that even a width-64 proxy is lighter
    acc = {w: cache.get_or_train(m, QUICK.with_width(w), progress=False)
           .meta["report"]["accuracy"] for w in (16, 64)}
    assert acc[64] > acc[16], acc  # the torus is hard enough that width pays off
    target = 0.5 * (acc[16] + acc[64])
    scene = scene_of(sphere(), m)
    plan = plan_proxies(scene, partition(scene, 2), target_accuracy=target, cache=cache,
                        config=QUICK, widths=(16, 64), train=False)
    d = plan.decisions[1]
    assert d.decision == "proxy" and d.width == 64
    assert d.tried == {16: acc[16], 64: acc[64]} and d.tried[16] < target <= d.accuracy
