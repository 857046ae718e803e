"""A pass's film sums do not depend on the order its contributions arrive in (steps group
rays by timing), and stay within float64 rounding of the plain sums."""

from __future__ import annotations

import numpy as np
import pytest

from nprt.workers.wavefront.shard import fixed_point_sums


@pytest.mark.parametrize("seed", range(4))
def test_film_sums_are_the_same_bytes_in_any_order(seed):
    rng = np.random.default_rng(seed)
    n, m = 64 * 64, 50_000
    idx = rng.integers(0, n, m)
    rgb = rng.random((m, 3)) ** 6 * 10.0 ** rng.uniform(-3, 4)  # fireflies beside dim light
    rgb[rng.random(m) < 0.3, rng.integers(0, 3)] = 0.0
    a = fixed_point_sums(idx, rgb, n)
    for _ in range(3):
        perm = rng.permutation(m)
        assert np.array_equal(fixed_point_sums(idx[perm], rgb[perm], n), a)
    plain = np.stack([np.bincount(idx, weights=rgb[:, c], minlength=n) for c in range(3)], 1)
    peak = rgb.max(axis=0)
    count = np.bincount(idx, minlength=n)[:, None]
    # bounded by the quantum: 2 * count * max / 2^62 per value, plus float64 rounding
    assert np.all(np.abs(a - plain) <= count * (4 * count * peak / 2.0**62)
                  + 1e-15 * np.abs(plain))


def test_film_sums_split_over_steps_equal_one_step():
    """Contributions kept step by step and summed at collect give one answer for any
    split into steps."""
    rng = np.random.default_rng(9)
    idx, rgb = rng.integers(0, 100, 5000), rng.random((5000, 3))
    whole = fixed_point_sums(idx, rgb, 100)
    cut = rng.permutation(5000)
    parts = np.array_split(cut, 7)
    again = fixed_point_sums(np.concatenate([idx[p] for p in parts]),
                             np.concatenate([rgb[p] for p in parts]), 100)
    assert np.array_equal(whole, again)
