"""The admission hot path's shortcuts give what the long way gives: job ids drawn from a
batch of random bytes, a job body's settings taken without validating them again, stored
as their JSON text, and the answer written from the stored row."""

from __future__ import annotations

import json
import os
import uuid

import pytest

from nprt.service.jobapi import new_job_id, settings_json
from nprt.service.schemas import JobCreate, JobPublic, queued_job_json
from nprt.service.store import JobStore
from nprt.workers.passes import count_passes
from nprt.workers.settings import RenderSettings

BODIES = [
    {"scene": "forest:tiny"},
    {"scene": "forest:tiny", "width": 32, "height": 16, "spp": 2, "seed": 7, "tile_size": 16,
     "spp_per_pass": 1, "russian_roulette": True},
    {"scene": "city", "shards": 3, "mode": "proxy", "frames": {"first": 1, "last": 2},
     "proxy": {"accuracy": "35dB", "band": 0.2, "check": True}},
    {"scene": "city", "shards": 2, "mode": "proxy", "proxy": {"shadow_band": 0.1}},
    {"scene": "ville \u00e9t\u00e9 \u2603 \"q\" \\ \n\t", "seed": (1 << 63) - 1,
     "proxy": {"accuracy": "exact", "width": 32, "threshold": 0.35}},
]


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


@pytest.mark.parametrize("body", BODIES)
def test_job_render_settings_equal_the_validated_settings(body):
    job = JobCreate.model_validate(body)
    fields = {k: v for k, v in body.items() if k not in ("scene", "frames")}
    expected = RenderSettings.model_validate(fields)
    got = job.render_settings()
    assert type(got) is RenderSettings
    assert got == expected
    assert got.model_dump(mode="json") == expected.model_dump(mode="json")


@pytest.mark.parametrize("body", BODIES)
def test_stored_settings_are_the_bodys_settings_fields_as_the_model_dumps_them(body, tmp_path):
    job = JobCreate.model_validate_json(json.dumps(body))
    expected = RenderSettings.model_validate(
        {k: v for k, v in body.items() if k not in ("scene", "frames")})
    text = settings_json(job)
    assert json.loads(text) == expected.model_dump(mode="json")  # no scene, no frames
    store = JobStore(tmp_path / "jobs.sqlite3")
    rec = store.insert("a", job.scene, text, 1)
    assert rec.settings == expected.model_dump(mode="json") == store.get("a").settings
    assert store.get("a").settings_json == text


@pytest.mark.parametrize("created_at", [None, 1_700_000_000.0, 1_700_000_000.5])
@pytest.mark.parametrize("body", BODIES)
def test_admission_answer_is_the_public_model_of_the_stored_job(body, created_at, tmp_path):
    job = JobCreate.model_validate_json(json.dumps(body))
    frames = None if job.frames is None else [job.frames.first, job.frames.last]
    store = JobStore(tmp_path / "jobs.sqlite3")
    rec = store.insert(new_job_id(), job.scene, settings_json(job), count_passes(job), None,
                       frames)
    if created_at is not None:  # a whole second has no fraction in ISO 8601
        rec.created_at = created_at
        store._db.execute("UPDATE jobs SET created_at = ? WHERE id = ?", (created_at, rec.id))
    answer = queued_job_json(rec, rec.settings_json)
    assert answer == JobPublic.from_record(rec, job.render_settings()).model_dump_json().encode()
    assert answer == JobPublic.from_record(store.get(rec.id)).model_dump_json().encode()
