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
