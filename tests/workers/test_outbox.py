"""A shard's outbox (nprt.workers.runtime.outbox): small parcels wait for company, and what
leaves is exactly what was put in, merged per target: every ray once, rays to be shaded
first, credits summed. When they leave: at min_rays, after wait_s, or on flush."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from nprt.workers.runtime.outbox import Outbox, merge
from nprt.workers.runtime.protocol import Parcel
from nprt.workers.wavefront.batch import FLAG_SHADE, RayBatch, ShadowRayBatch
from nprt.workers.wavefront.shard import _split_settled
from tests.workers.test_batch_glue import _random, _same


def _parcel(rng, rays: int, shadow: int = 0, settled: int = 0, camera: int = 0,
            credits=None) -> Parcel:
    """A parcel as `Shard._pack` makes one: its first `settled` rays flagged to be shaded."""
    batch = None
    if rays:
        batch = _random(RayBatch, rng, rays)
        flags = batch.flags & np.uint8(~FLAG_SHADE & 0xFF)
        flags[:settled] |= FLAG_SHADE
        batch = batch.replace(flags=flags)
    sh = _random(ShadowRayBatch, rng, shadow) if shadow else None
    cam = ((rng.integers(0, 1 << 20, camera).astype(np.uint32),
            rng.integers(0, 64, camera).astype(np.uint32)) if camera else None)
    return Parcel(-1, credits or {0: Fraction(1, 4)}, batch, sh, camera=cam)


def test_merge_keeps_every_ray_once_with_rays_to_shade_first():
    rng = np.random.default_rng(0)
    parts = [_parcel(rng, 7, 3, settled=2, camera=4, credits={1: Fraction(1, 3)}),
             _parcel(rng, 0, 5, credits={1: Fraction(1, 6), 2: Fraction(1, 2)}),
             _parcel(rng, 9, 0, settled=4, camera=2, credits={2: Fraction(1, 8)})]
    out = merge(parts)
    assert out.credits == {1: Fraction(1, 2), 2: Fraction(5, 8)}
    assert out.n_rays == sum(p.n_rays for p in parts)
    # The receiver's split gives the same settled and other rays as from the parcels apart.
    arrived, rest = _split_settled([out.rays], [])
    want_arrived, want_rest = _split_settled([p.rays for p in parts if p.rays is not None], [])
    _same(arrived, want_arrived)
    _same(rest, want_rest)
    assert (out.rays.flags[:6] & FLAG_SHADE).all() and not (out.rays.flags[6:] & FLAG_SHADE).any()
    _same(out.shadow, ShadowRayBatch.concat([p.shadow for p in parts if p.shadow is not None]))
    for got, want in zip(out.camera, zip(*[p.camera for p in parts if p.camera], strict=True),
                         strict=True):
        np.testing.assert_array_equal(got, np.concatenate(want))


def test_a_single_parcel_leaves_as_it_is():
    p = _parcel(np.random.default_rng(1), 5)
    assert merge([p]) is p


def test_small_parcels_wait_until_they_carry_min_rays_together():
    rng = np.random.default_rng(2)
    box = Outbox(3, min_rays=20, wait_s=10.0)
    left = box.put([None, _parcel(rng, 8), _parcel(rng, 25)], now=0.0, flush=False)
    assert [t for t, _ in left] == [2] and box.held_rays == 8  # 25 rays leave at once
    left = box.put([None, _parcel(rng, 8), None], now=1.0, flush=False)
    assert left == [] and box.held_rays == 16
    left = box.put([None, _parcel(rng, 4), None], now=2.0, flush=False)
    assert [(t, p.n_rays) for t, p in left] == [(1, 20)] and box.held_rays == 0


def test_a_held_parcel_leaves_after_wait_s_or_on_flush():
    rng = np.random.default_rng(3)
    box = Outbox(2, min_rays=1000, wait_s=0.02)
    assert box.put([_parcel(rng, 3), None], now=5.0, flush=False) == []
    assert box.put([None, _parcel(rng, 2)], now=5.01, flush=False) == []
    left = box.put([None, None], now=5.025, flush=False)  # target 0's has waited 25 ms
    assert [(t, p.n_rays) for t, p in left] == [(0, 3)]
    left = box.put([_parcel(rng, 1), None], now=5.03, flush=True)
    assert sorted((t, p.n_rays) for t, p in left) == [(0, 1), (1, 2)] and box.held_rays == 0


def test_without_min_rays_every_parcel_leaves_at_once():
    rng = np.random.default_rng(4)
    box = Outbox(2)
    parcels = [_parcel(rng, 1), _parcel(rng, 2)]
    assert box.put(parcels, now=0.0, flush=False) == list(enumerate(parcels))


def test_negative_settings_and_orders_are_refused():
    with pytest.raises(ValueError, match="negative"):
        Outbox(2, min_rays=-1)
    order = Parcel(-1, {0: Fraction(1)}, orders=(object(),))
    with pytest.raises(ValueError, match="orders"):
        merge([order, _parcel(np.random.default_rng(5), 2)])
