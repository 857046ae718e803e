"""The accuracy target's arithmetic (nprt.proxies.accuracy) and the check's sampling and
statistics (nprt.proxies.check), without a render."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nprt.proxies import accuracy as acc
from nprt.proxies.check import BLOCK, block_psnr, check_blocks, verdict
from nprt.proxies.evaluate import CURVE_BANDS

# A curve whose errors fall with the band: fn (what secondary rays pay) is half of fp + fn.
RATES = np.array([0.08, 0.06, 0.04, 0.03, 0.02, 0.01, 0.005, 0.002, 0.001, 5e-4, 2e-4, 1e-4,
                  0.0])
CURVE = {"band": list(CURVE_BANDS), "share": list(1 - np.asarray(CURVE_BANDS)),
         "fp": list(RATES / 2), "fn": list(RATES / 2)}


class _P:
    def __init__(self, curve):
        self.meta = {"report": {"curve": curve}}


@pytest.mark.parametrize("text, value", [("40dB", 40.0), ("35.5 dB", 35.5), ("40", 40.0),
                                         (30, 30.0), ("exact", "exact"), ("EXACT", "exact"),
                                         (None, None)])
def test_accuracy_parses_decibels_and_exact(text, value):
    assert acc.parse_accuracy(text) == value


@pytest.mark.parametrize("bad", ["fast", "40 dBm", -3, 5, 150, True])
def test_accuracy_refuses_what_is_not_a_psnr_with_the_value_named(bad):
    with pytest.raises(ValueError, match=str(bad)[:2]):
        acc.parse_accuracy(bad)


def test_a_higher_target_never_trusts_more_and_exact_trusts_nothing():
    for kind in acc.KINDS:
        bands = [acc.choose_band(CURVE, kind, t) for t in (20, 30, 40, 50, 60, 90)]
        assert bands == sorted(bands), (kind, bands)
        assert acc.choose_band(CURVE, kind, acc.EXACT) == 1.0
        assert acc.choose_band(None, kind, 20) == 1.0  # no curve: nothing is trusted


def test_a_porous_proxy_is_trusted_by_secondary_rays_but_not_by_shadow_rays():
    """A leaf cloud's proxy says "occluded" where light gets through (false positives only):
    a secondary ray sent to a wrong hit is settled exactly there, a shadow ray is darkened."""
    porous = {**CURVE, "fp": list(RATES * 5), "fn": [0.0] * len(RATES)}
    assert acc.choose_band(porous, "secondary", 40) == 0.0
    assert acc.choose_band(porous, "shadow", 40) > acc.choose_band(CURVE, "shadow", 40)


def test_the_chosen_band_meets_the_budget_the_prediction_assumes():
    """With the prior query count per ray, each kind's error is within its half of the
    target's squared error, so the prediction meets the target."""
    proxies = {1: _P(CURVE), 2: _P(CURVE)}
    for t in (25.0, 35.0):
        bands = acc.mesh_bands(proxies, t)
        prior = acc.prior_queries(proxies, {1: 3.0, 2: 1.0})
        assert acc.predict_error(proxies, bands, prior).psnr_db >= t - 1e-9


def test_measured_queries_are_per_ray_of_each_kind():
    counters = {acc.counter_name("shadow", 2): 50, acc.counter_name("secondary", 2): 10,
                "proxy_queries": 99}
    got = acc.measured_queries(counters, {"shadow": 100, "secondary": 20})
    assert got == {"secondary": {2: 0.5}, "shadow": {2: 0.5}}


def test_check_blocks_are_whole_distinct_seeded_and_about_one_in_64():
    a = check_blocks(1024, 768, seed=3)
    assert len(a) == math.ceil(1024 * 768 / BLOCK**2 / 64)
    assert len({tuple(c) for c in a}) == len(a)
    assert (a % BLOCK == 0).all() and (a[:, 0] <= 1024 - BLOCK).all()
    assert (a[:, 1] <= 768 - BLOCK).all()
    assert np.array_equal(a, check_blocks(1024, 768, seed=3))
    assert not np.array_equal(a, check_blocks(1024, 768, seed=4))
    assert len(check_blocks(64, 48, seed=0)) == 32  # at least 32 blocks where there are


def test_block_psnr_interval_brackets_the_estimate_and_a_miss_is_loud():
    rng = np.random.default_rng(0)
    ref = rng.uniform(0.1, 0.8, (20, BLOCK, BLOCK, 3))
    test = ref * (1 + rng.normal(0, 0.02, ref.shape))
    m = block_psnr(ref, test)
    lo, hi = m["interval_db"]
    assert lo <= m["psnr_db"] <= hi and m["blocks"] == 20
    assert block_psnr(ref, ref)["psnr_db"] is None  # identical: infinite PSNR
    assert verdict(30.0, 35.0, m)["met"] is (hi >= 30.0)
    missed = verdict(hi + 1.0, 50.0, m)
    assert missed["met"] is False and "ACCURACY TARGET MISSED" in missed["warning"]
