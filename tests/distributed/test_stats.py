"""Render statistics of the distributed renderer add up: transfers, hops and bytes."""

from __future__ import annotations

import numpy as np
import pytest

from nprt.workers.render import render
from nprt.workers.wavefront.batch import KIND_NAMES
from tests.distributed.helpers import RAY_ROW_BYTES, SHADOW_ROW_BYTES, settings

SCENE = "city"  # the most secondary rays of the three demos


@pytest.fixture(scope="module")
def results_by_k(ray_local, scenes) -> dict:
    return {k: render(scenes[SCENE], settings(k)) for k in (1, 2, 4)}


@pytest.fixture(scope="module")
def stats_by_k(results_by_k) -> dict:
    return {k: r.stats.to_dict() for k, r in results_by_k.items()}


@pytest.mark.parametrize("k", (1, 2, 4), ids=lambda k: f"k{k}")
def test_shard_cpu_splits_into_the_wavefront_thread_and_the_rest(results_by_k, k):
    """A shard's process CPU counts every thread; the wavefront thread's own share is
    reported beside it, so what Ray's threads cost is their difference."""
    info = results_by_k[k].info
    total = info["coordinator_cpu_s"]
    for sh in info["shard_stats"]:
        assert 0 < sh["wavefront_cpu_s"] <= sh["cpu_s"], sh
        total += sh["cpu_s"]
    assert info["cpu_s"] == pytest.approx(total, abs=1e-3)


def test_transfers_are_zero_for_one_shard_and_positive_for_more(stats_by_k):
    one = stats_by_k[1]
    assert one["total_transfers"] == 0 and one["total_bytes"] == 0, one
    assert one["hops_histogram"] == one["hops_histogram"][:1], "hops > 0 with one shard"
    for k in (2, 4):
        st = stats_by_k[k]
        assert st["total_transfers"] > 0 and st["total_bytes"] > 0, (k, st)
        assert all(st["transfers"][kind] > 0 for kind in KIND_NAMES), (k, st["transfers"])
        assert len(st["hops_histogram"]) > 1, (k, st["hops_histogram"])


@pytest.mark.parametrize("k", (1, 2, 4), ids=lambda k: f"k{k}")
def test_hops_histogram_counts_every_finished_ray_once(stats_by_k, references, k):
    """Every ray the reference traced (camera, BSDF and shadow rays, occluded or not)
    finishes exactly once somewhere, whatever the number of shards."""
    ref_rays = references[SCENE].stats.to_dict()["rays"]
    hist = np.asarray(stats_by_k[k]["hops_histogram"])
    assert hist.sum() == sum(ref_rays.values()), (k, hist.tolist(), ref_rays)
    # And its transfers are the hops that rays made (a ray moves once per hop).
    hops = int((hist * np.arange(len(hist))).sum())
    assert hops == stats_by_k[k]["total_transfers"], (k, hops, stats_by_k[k]["transfers"])


CAMERA_NAME_BYTES = 8  # pixel, sample: uint32 each


@pytest.mark.parametrize("k", (1, 2, 4), ids=lambda k: f"k{k}")
def test_bytes_by_kind_equal_transfers_times_row_bytes(stats_by_k, k):
    st = stats_by_k[k]
    per_row = {"primary": RAY_ROW_BYTES, "secondary": RAY_ROW_BYTES, "shadow": SHADOW_ROW_BYTES}
    # Camera rays go to the owner of their first box by name: (pixel, sample), 8 bytes.
    by_name = st["counters"].get("camera_rays_sent_by_name", 0)
    assert (by_name > 0) == (k > 1)
    for kind in KIND_NAMES:
        named = by_name if kind == "primary" else 0
        want = (st["transfers"][kind] - named) * per_row[kind] + named * CAMERA_NAME_BYTES
        assert st["bytes"][kind] == want, (kind, st)
    assert st["total_bytes"] == sum(st["bytes"].values())
    assert st["total_transfers"] == sum(st["transfers"].values())


def test_row_bytes_match_the_declared_layout():
    # origin 3 x f64 (precision far from the origin); direction, throughput 3 x f32; tmax,
    # pdf_prev, hit_u, hit_v f32; pixel, sample u32; hit_inst, hit_prim i32; visited u64;
    # depth, kind, hops, flags u8.
    assert RAY_ROW_BYTES == 24 + 2 * 12 + 4 * 4 + 2 * 4 + 2 * 4 + 8 + 4 * 1
    # origin 3 x f64; direction, contribution 3 x f32; tmax f32; pixel u32; visited u64;
    # hops u8.
    assert SHADOW_ROW_BYTES == 24 + 2 * 12 + 4 + 4 + 8 + 1


@pytest.mark.parametrize("k", (1, 2, 4), ids=lambda k: f"k{k}")
def test_camera_rays_are_generated_once_per_path(stats_by_k, k):
    """One shard per pass makes its camera rays (others get them by name): over all
    shards, as many as the pass has paths, none twice."""
    c = stats_by_k[k]["counters"]
    assert c["camera_rays_generated"] == c["paths"] > 0, c
    assert c.get("camera_rays_sent_by_name", 0) <= c["paths"]
