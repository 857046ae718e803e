"""Sharded (Ray) jobs through the service: concurrent jobs share one Ray, and exact mode
with K shards gives the reference image."""

from __future__ import annotations

import httpx
import numpy as np
import pytest

from tests.service.helpers import TINY, LiveServer, png_pixels, settings_for, wait_for


@pytest.mark.slow
def test_concurrent_sharded_exact_jobs_match_reference_job(tmp_path):
    pytest.importorskip("ray")
    with LiveServer(settings_for(tmp_path, max_concurrent_jobs=3)) as server, \
            httpx.Client(base_url=server.url, timeout=30.0) as client:
        jobs = {k: client.post("/v1/jobs", json={"scene": "forest:tiny", **TINY, "shards": k}
                               ).json()["id"] for k in (0, 2, 3)}
        done = {}
        for k, job_id in jobs.items():
            done[k] = wait_for(lambda j=job_id: (r := client.get(f"/v1/jobs/{j}").json())
                               ["state"] in ("succeeded", "failed") and r, 300,
                               interval_s=0.2, what=f"{k}-shard job")
        for k, job in done.items():
            assert job["state"] == "succeeded", (k, job["error"])
        assert done[0]["stats"]["renderer"] == "reference"
        assert done[2]["stats"]["renderer"] == done[3]["stats"]["renderer"] == "distributed"
        assert done[2]["stats"]["total_transfers"] > 0  # rays really moved between shards
        ref = png_pixels(client.get(f"/v1/jobs/{jobs[0]}/image.png").content).astype(int)
        for k in (2, 3):
            img = png_pixels(client.get(f"/v1/jobs/{jobs[k]}/image.png").content).astype(int)
            # Float summation order differs between shards: allow one 8-bit step.
            assert np.abs(img - ref).max() <= 1, f"{k} shards differ from the reference"


@pytest.mark.slow
def test_second_job_on_a_scene_reuses_its_warm_shard_pool(tmp_path):
    pytest.importorskip("ray")
    with LiveServer(settings_for(tmp_path, max_concurrent_jobs=1)) as server, \
            httpx.Client(base_url=server.url, timeout=30.0) as client:
        manager = server.scheduler
        done = []
        for seed in (1, 2):  # a different job (seed) on the same scene and placement
            job_id = client.post("/v1/jobs", json={"scene": "forest:tiny", **TINY, "shards": 2,
                                                   "seed": seed}).json()["id"]
            done.append(wait_for(lambda j=job_id: (r := client.get(f"/v1/jobs/{j}").json())
                                 ["state"] in ("succeeded", "failed") and r, 300,
                                 interval_s=0.1, what="sharded job"))
            if seed == 1:
                (pool,) = manager.pools._pools.values()
                actors = [a._actor_id.hex() for a in pool.actors]
        assert [j["state"] for j in done] == ["succeeded", "succeeded"], done
        first, second = (j["stats"] for j in done)
        assert not first["warm_pool"] and second["warm_pool"]
        assert [s["pid"] for s in first["shard_stats"]] == [s["pid"] for s in second["shard_stats"]]
        (same,) = manager.pools._pools.values()
        assert same is pool and [a._actor_id.hex() for a in same.actors] == actors
        assert manager.pools.started == 1, "the second job started shard actors"
        # Different seeds on one pool: the per-job settings did reach the shards.
        a = png_pixels(client.get(f"/v1/jobs/{done[0]['id']}/image.png").content)
        b = png_pixels(client.get(f"/v1/jobs/{done[1]['id']}/image.png").content)
        assert (a != b).any()
