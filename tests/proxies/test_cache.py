"""The proxy cache: round trip, shipped fallback, bad files retrained, wrong keys unused,
and a clear ProxyUnavailable (an exact fallback in the plan) when torch is missing."""

from __future__ import annotations

import sys

import pytest

from nprt.proxies.cache import ProxyCache, ProxyUnavailable, file_name
from nprt.proxies.config import ProxyConfig
from nprt.proxies.policy import plan_proxies
from nprt.scene.partition import partition
from tests.proxies.helpers import scene_of, sphere, stand_in_proxy, torus

TINY = ProxyConfig(width=16, steps=40, n_samples=4096, grid=8,
                   eval_samples=2048)


@pytest.fixture
def cache(tmp_path):
    return ProxyCache(tmp_path / "user", shipped_dir=tmp_path / "shipped")


def test_put_then_get_round_trips_the_blob(cache):
    m = sphere()
    p = stand_in_proxy(m, TINY)
    path = cache.put(m, TINY, p)
    assert path is not None and path.name == file_name(m, TINY)
    got = cache.get(m, TINY)
    assert got is not None and got.to_bytes() == p.to_bytes()


def test_shipped_dir_is_used_when_the_user_cache_misses(cache):
    m = sphere()
    p = stand_in_proxy(m, TINY)
    shipped = ProxyCache(cache.shipped_dir, shipped_dir=None)
    shipped.put(m, TINY, p)
    assert not (cache.dir / file_name(m, TINY)).exists()
    assert cache.get(m, TINY).to_bytes() == p.to_bytes()


def test_a_mismatched_config_or_mesh_is_not_used(cache):
    m, other = sphere(), torus()
    cache.put(m, TINY, stand_in_proxy(m, TINY))
    wider = TINY.with_width(32)
    assert cache.get(m, wider) is None
    blob = (cache.dir / file_name(m, TINY)).read_bytes()
    (cache.dir / file_name(m, wider)).write_bytes(blob)  # right name, wrong content
    (cache.dir / file_name(other, TINY)).write_bytes(blob)
    assert cache.get(m, wider) is None
    assert cache.get(other, TINY) is None
    reasons = " ".join(why for _, why in cache.rejected)
    assert "config key" in reasons and "mesh hash" in reasons


@pytest.mark.parametrize("damage", ["flip", "truncate"])
def test_a_corrupted_file_is_detected_and_retrained(cache, damage):
    pytest.importorskip("torch", reason="retraining needs PyTorch")
    m = sphere()
    cache.put(m, TINY, stand_in_proxy(m, TINY))
    path = cache.dir / file_name(m, TINY)
    blob = bytearray(path.read_bytes())
    if damage == "flip":
        blob[-20] ^= 0x55
    else:
        blob = blob[: len(blob) // 2]
    path.write_bytes(bytes(blob))
    assert cache.get(m, TINY) is None
    assert "sha256" in cache.rejected[-1][1] or "truncated" in cache.rejected[-1][1]
    fresh = cache.get_or_train(m, TINY, progress=False)
    assert fresh.meta["report"]["eval_rays"] == TINY.eval_samples  # really trained
    assert cache.get(m, TINY).to_bytes() == fresh.to_bytes()


@pytest.fixture
def no_torch(monkeypatch):
    """Make `import torch` fail as on an install without the 'train' extra."""
    monkeypatch.setitem(sys.modules, "torch", None)
    for mod in ("nprt.proxies.train", "nprt.proxies.model", "nprt.proxies.export"):
        monkeypatch.delitem(sys.modules, mod, raising=False)


def test_without_torch_get_or_train_raises_proxy_unavailable(cache, no_torch):
    m = torus()
    with pytest.raises(ProxyUnavailable, match="PyTorch") as err:
        cache.get_or_train(m, TINY, progress=False)
    assert m.name in str(err.value) and "nprt[train]" in str(err.value)


def test_without_torch_a_cached_proxy_is_still_served(cache, no_torch):
    m = torus()
    cache.put(m, TINY, stand_in_proxy(m, TINY))
    assert cache.get_or_train(m, TINY, progress=False) is not None


def test_without_torch_the_plan_falls_back_to_exact_with_the_reason(cache, no_torch):
    scene = scene_of(sphere(), torus())
    plan = plan_proxies(scene, partition(scene, 2), cache=cache, config=TINY)
    assert [d.decision for d in plan.decisions] == ["fallback", "fallback"]
    assert all("PyTorch" in d.reason for d in plan.decisions)
    assert plan.proxies == {} and plan.to_dict()["counts"]["fallback"] == 2
