"""Numerical stability at the extremes, exact mode on K = 3 shards: a small scene moved
by any similarity (translation up to 1e7, scale 1e-6 to 1e6) renders the same image
within noise as the untouched scene's reference."""

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

K = 3


@pytest.fixture(scope="module")
def untransformed():
    scene = small_scene()
    return tuple(render_image(scene, **SETTINGS, seed=s) for s in SEEDS)


@pytest.mark.slow  # a Coordinator per example: about 10 s each on 2 shared cores
@settings(max_examples=2, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(m=similarities())
@example(m=similarity(1e-6, (-1e7, 1e7, 1e7), 75.0))
@example(m=similarity(1e6, (1e7, -1e7, -1e7)))
def test_similarity_transform_leaves_the_exact_image_unchanged(ray_local, untransformed,
                                                               tmp_path, m):
    ref, ref2 = untransformed
    img = render_image(transform_scene(small_scene(), m), **SETTINGS, seed=SEEDS[0],
                       shards=K)
    assert_same_within_noise(tmp_path, f"moved_exact_k{K}", img, ref, ref2)
