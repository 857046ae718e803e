"""Numerical stability at the extremes (reference renderer): a small scene moved by any
similarity, translation up to 1e7 in any direction and uniform scale from 1e-6 to 1e6
with radiometry adjusted (nprt.scene.transform), renders the same image within noise."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, example, given, settings

from nprt.scene.transform import similarity, transform_scene
from tests.workers.extremes import (
    SEEDS,
    SETTINGS,
    assert_same_within_noise,
    similarities,
    small_scene,
)
from tests.workers.helpers import render_image


@pytest.fixture(scope="module")
def untransformed():
    scene = small_scene()
    return tuple(render_image(scene, **SETTINGS, seed=s) for s in SEEDS)


@settings(max_examples=8, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(m=similarities())
@example(m=similarity(1e-6, (1e7, -1e7, 1e7)))
@example(m=similarity(1e6, (-1e7, 0.0, 3e6), 30.0))
@example(m=similarity(1.0, (2.5e5, 1e7, -4e6)))
def test_similarity_transform_leaves_the_image_unchanged(untransformed, tmp_path, m):
    ref, ref2 = untransformed
    img = render_image(transform_scene(small_scene(), m), **SETTINGS, seed=SEEDS[0])
    assert_same_within_noise(tmp_path, "moved_reference", img, ref, ref2)
