"""Exact (Wald-style) forwarding reproduces the single-process reference for any K, bit for
bit: the film sums are the same float64 bytes."""

from __future__ import annotations

import pytest

from nprt.workers.render import render
from tests.distributed.helpers import SCENES, assert_identical, settings

SHARD_COUNTS = (1, 2, 3, 4, 8)


@pytest.mark.parametrize("k", SHARD_COUNTS, ids=lambda k: f"k{k}")
@pytest.mark.parametrize("name", SCENES)
def test_exact_matches_reference_for_any_shard_count(ray_local, scenes, references, tmp_path,
                                                     name, k):
    result = render(scenes[name], settings(k))
    assert result.info["renderer"] == "distributed" and result.info["shards"] == k
    assert_identical(tmp_path, f"{name}_k{k}", result, references[name])
