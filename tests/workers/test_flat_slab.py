"""The walks' flat top level: the slab without NaN handling that finite rays take gives
the same crossings and entry distances as the NaN-aware one, and awkward rays (zero or
non-finite components, origins on box planes) still take the NaN-aware one."""

from __future__ import annotations

import numpy as np
import pytest

from nprt.workers.kernels import crossings
from nprt.workers.kernels.bvh import _slab_planes, _slab_planes_finite
from nprt.workers.traversal.toplevel import InstanceTable
from tests.workers.test_toplevel import _random_scene, _rays


def _flat_of(boxes):
    return np.ascontiguousarray(boxes.reshape(len(boxes), 6).T)


@pytest.mark.parametrize("seed", [0, 1])
def test_finite_slab_equals_the_nan_aware_slab_on_finite_rays(seed):
    rng = np.random.default_rng(seed)
    boxes = InstanceTable(_random_scene(rng, 40)).world_bounds
    o, d, tmax = _rays(rng, boxes, 4000, 10.0)
    # Finite rays only, some far away and some with tiny direction components (huge 1 / d).
    d = np.where((d == 0) | ~np.isfinite(d), np.float32(1e-30), d).astype(np.float64)
    o = np.where(np.isfinite(o), o, 1.0).astype(np.float64)
    o[::7] *= 1e6
    tm = np.where(np.isnan(tmax), 1.0, tmax).astype(np.float64)
    inv = 1.0 / d
    assert np.isfinite(inv).all() and (inv != 0).all()
    crossed = 0
    for r in range(len(o)):
        for j in range(len(boxes)):
            args = (*boxes[j, 0], *boxes[j, 1], *o[r], *inv[r], tm[r])
            want, got = _slab_planes(*args), _slab_planes_finite(*args)
            assert bool(want[0]) == bool(got[0]), (r, j, want, got)
            if want[0]:
                assert want[1] == got[1] and want[2] == got[2], (r, j, want, got)
                crossed += 1
    assert crossed > len(o) // 2, f"only {crossed} crossings: the rays test too little"


@pytest.mark.parametrize("seed", [2, 3])
def test_flat_queue_is_the_nan_aware_queue_on_awkward_rays(seed):
    rng = np.random.default_rng(seed)
    boxes = InstanceTable(_random_scene(rng, 30)).world_bounds
    flat = _flat_of(boxes)
    members = np.arange(len(boxes), dtype=np.int64) * 3 + 1  # ids differ from columns
    o, d, tmax = _rays(rng, boxes, 3000, 10.0)
    o, d, tm = o.astype(np.float64), d.astype(np.float64), tmax.astype(np.float64)
    k = len(boxes)
    te, ok = np.empty(k), np.empty(k, np.bool_)
    q_t, q_id = np.empty(k + 1), np.empty(k + 1, np.int64)
    for r in range(len(o)):
        with np.errstate(divide="ignore"):
            i = 1.0 / d[r]
        want = []
        for j in range(k):
            hit, t_enter, _ = _slab_planes(*boxes[j, 0], *boxes[j, 1], *o[r], *i, tm[r])
            if hit:
                want.append((t_enter, members[j]))
        h = crossings._flat_queue(flat, True, members, *o[r], *i, tm[r], te, ok, q_t, q_id)
        got = sorted(zip(q_t[:h].tolist(), q_id[:h].tolist(), strict=True))
        assert got == sorted(want), (r, o[r], d[r], tm[r])
        assert list(q_t[:h]) == sorted(q_t[:h], reverse=True), "not kept farthest first"
