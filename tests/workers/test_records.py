"""The compiled hit-record folds (nprt.workers.kernels.records) against the numpy rule
they mirror (`batch.precedes`), on records full of ties: equal t, lights against
instances, no hit, equal instances with other primitives."""

from __future__ import annotations

import numpy as np

from nprt.workers.kernels import records
from nprt.workers.wavefront.batch import LIGHT_BASE, NO_HIT, precedes


def _records(rng, n):
    t = rng.choice(np.array([0.5, 1.0, 1.0, 2.0, np.inf], np.float32), n)
    inst = rng.choice(np.array([NO_HIT, LIGHT_BASE, LIGHT_BASE - 1, 0, 1, 1, 5], np.int32), n)
    prim = rng.integers(-1, 3, n).astype(np.int32)
    u, v = rng.random(n, np.float32), rng.random(n, np.float32)
    return t, inst, prim, u, v


def test_precedes1_is_batch_precedes():
    rng = np.random.default_rng(1)
    a, b = _records(rng, 5000), _records(rng, 5000)
    want = precedes(a[0], a[1], a[2], b[0], b[1], b[2])
    got = [records.precedes1(a[0][i], a[1][i], a[2][i], b[0][i], b[1][i], b[2][i])
           for i in range(5000)]
    assert np.array_equal(got, want)


def test_folds_equal_the_numpy_folds_they_replace():
    rng = np.random.default_rng(2)
    n = 20000
    run_t, run_inst, run_prim, run_u, run_v = _records(rng, n)
    run_inst = np.where(run_inst < 0, -1, run_inst).astype(np.int32)  # local: -1 or instance
    tmax, rec_inst, rec_prim, rec_u, rec_v = _records(rng, n)
    light_t = rng.choice(np.array([0.5, 1.0, 2.0, np.inf], np.float32), n)
    light = rng.integers(-1, 2, n).astype(np.int32)
    for use_record in (True, False):
        got = records.local_winners(run_t, run_inst, run_prim, run_u, run_v, tmax, rec_inst,
                                    rec_prim, use_record)
        better = (run_inst >= 0) & (precedes(run_t, run_inst, run_prim, tmax, rec_inst,
                                             rec_prim) if use_record else run_t < tmax)
        want = (np.where(better, run_t, tmax), np.where(better, run_inst, -1),
                np.where(better, run_prim, -1), np.where(better, run_u, 0), np.where(better,
                                                                                   run_v, 0))
        for g, w in zip(got, want, strict=True):
            assert np.array_equal(g, w)
    t, inst, prim, u, v = got
    out = records.with_lights(t, inst, prim, u, v, rec_inst, rec_prim, rec_u, rec_v,
                              light_t, light)
    have = inst >= 0
    h_inst, h_prim = np.where(have, inst, rec_inst), np.where(have, prim, rec_prim)
    lit = (light >= 0) & precedes(light_t, LIGHT_BASE - light, np.full(n, -1), t, h_inst,
                                  h_prim)
    assert 0 < lit.sum() < n
    want = (np.where(lit, light_t, t), np.where(lit, LIGHT_BASE - light, h_inst),
            np.where(lit, -1, h_prim), np.where(have & ~lit, u, np.where(lit, 0, rec_u)),
            np.where(have & ~lit, v, np.where(lit, 0, rec_v)))
    for g, w in zip(out, want, strict=True):
        assert np.array_equal(g, w)
    assert [a.dtype for a in out] == [np.float32, np.int32, np.int32, np.float32, np.float32]
