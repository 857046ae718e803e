"""The admission hot path's shortcuts give what the long way gives: job ids drawn from a
batch of random bytes, and a job body's settings taken without validating them again."""

from __future__ import annotations

import os
import uuid

import pytest

from nprt.service.jobapi import new_job_id
from nprt.service.schemas import JobCreate
from nprt.workers.settings import RenderSettings


def test_job_ids_are_distinct_uuid4_hex_and_a_forked_child_draws_its_own():
    ids = [new_job_id() for _ in range(3 * 256 + 5)]  # across several batches
    assert len(set(ids)) == len(ids)
    assert all(uuid.UUID(i).version == 4 and uuid.UUID(i).hex == i for i in ids)
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child's first id must not be the parent's next one
        os.write(write, new_job_id().encode())
        os._exit(0)
    os.close(write)
    os.waitpid(pid, 0)
    child = os.read(read, 64).decode()
    os.close(read)
    assert child != new_job_id() and child not in ids


@pytest.mark.parametrize("body", [
    {"scene": "forest:tiny"},
    {"scene": "forest:tiny", "width": 32, "height": 16, "spp": 2, "seed": 7, "tile_size": 16,
     "spp_per_pass": 1, "russian_roulette": True},
    {"scene": "city", "shards": 3, "mode": "proxy", "frames": {"first": 1, "last": 2},
     "proxy": {"accuracy": "35dB", "band": 0.2, "check": True}},
    {"scene": "city", "shards": 2, "mode": "proxy", "proxy": {"shadow_band": 0.1}},
])
def test_job_render_settings_equal_the_validated_settings(body):
    job = JobCreate.model_validate(body)
    fields = {k: v for k, v in body.items() if k not in ("scene", "frames")}
    expected = RenderSettings.model_validate(fields)
    got = job.render_settings()
    assert type(got) is RenderSettings
    assert got == expected
    assert got.model_dump(mode="json") == expected.model_dump(mode="json")
