"""A pass's film sums depend neither on the order its contributions arrive in (steps group
rays by timing) nor on how they are split over shards (K), and stay within float64
rounding of the plain sums."""

from __future__ import annotations

import numpy as np
import pytest

from nprt.workers.filmsum import LSB_EXP, MAX_EXP, FilmSums
from nprt.workers.kernels.filmsum import accumulate


def film(idx: np.ndarray, rgb: np.ndarray, n: int) -> FilmSums:
    out = FilmSums.zeros(n)
    outside = np.zeros(len(idx), bool)
    assert accumulate(idx, rgb, out.words, outside) == outside.sum()
    return out


def contributions(seed: int, n: int, m: int):
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, n, m)
    rgb = rng.random((m, 3)) ** 6 * 10.0 ** rng.uniform(-3, 4, (m, 1))  # fireflies, dim light
    rgb[rng.random(m) < 0.3, rng.integers(0, 3)] = 0.0
    return rng, idx, rgb


@pytest.mark.parametrize("seed", range(4))
def test_film_sums_are_the_same_bytes_in_any_order(seed):
    n, m = 64 * 64, 50_000
    rng, idx, rgb = contributions(seed, n, m)
    a = film(idx, rgb, n)
    for _ in range(3):
        perm = rng.permutation(m)
        assert np.array_equal(film(idx[perm], rgb[perm], n).words, a.words)
    plain = np.stack([np.bincount(idx, weights=rgb[:, c], minlength=n) for c in range(3)], 1)
    count = np.bincount(idx, minlength=n)[:, None]
    # one rounding to the quantum per value, plus the float64 rounding of the plain sum
    # (count additions) and of the conversion
    assert np.all(np.abs(a.to_float() - plain)
                  <= count * 2.0 ** (LSB_EXP - 1) + (count + 2) * 2.0**-52 * np.abs(plain))


@pytest.mark.parametrize("shards", (2, 3, 8))
def test_film_sums_split_over_shards_equal_one_shard(shards):
    """Any split of the contributions into shares (steps or shards), added in any order,
    gives the same integers and the same float64 bytes as one share."""
    n, m = 500, 20_000
    rng, idx, rgb = contributions(shards, n, m)
    whole = film(idx, rgb, n)
    owner = rng.integers(0, shards, m)
    for order in (range(shards), reversed(range(shards))):
        total = FilmSums.zeros(n)
        for s in order:
            total += film(idx[owner == s], rgb[owner == s], n)
        assert np.array_equal(total.words, whole.words)
        assert np.array_equal(total.to_float(), whole.to_float())
        assert np.all((total.words[..., 1] >= 0) & (total.words[..., 1] < 2**60))


def test_film_sums_keep_negative_and_tiny_values_exactly():
    idx = np.array([0, 0, 1, 1])
    rgb = np.array([[1.5, -2.25, 2.0 ** LSB_EXP], [-1.5, 2.25, 3 * 2.0 ** LSB_EXP],
                    [-(2.0 ** 39), 0.0, 0.0], [2.0 ** 39 + 0.5, 0.0, 0.0]])
    got = film(idx, rgb, 2).to_float()
    assert got[0].tolist() == [0.0, 0.0, 4 * 2.0 ** LSB_EXP]
    assert got[1].tolist() == [0.5, 0.0, 0.0]


def test_values_beyond_the_words_are_flagged_not_lost():
    idx = np.array([0, 1, 1])
    rgb = np.array([[2.0 ** MAX_EXP, 1.0, 0.0], [np.inf, 0.0, 0.0], [1.0, np.nan, 0.0]])
    out, outside = FilmSums.zeros(2), np.zeros(3, bool)
    assert accumulate(idx, rgb, out.words, outside) == 3
    assert outside.all()
    # the in-range channels of a flagged row are still in the words
    assert out.to_float()[0, 1] == 1.0 and out.to_float()[1, 0] == 1.0
