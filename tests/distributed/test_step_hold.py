"""A shard that holds its wavefront thread for more rays (nprt.workers.runtime.remote,
HOLD_RAYS / HOLD_S), holds small parcels back for company (SEND_RAYS / SEND_S,
nprt.workers.runtime.outbox), or sends parcels before its step ends (EMIT_RAYS) only
groups rays into other steps and parcels: exact mode still equals the reference bit for
bit, whether nothing waits, everything does, or every iteration sends."""

from __future__ import annotations

import pytest

from nprt.workers.render import render
from nprt.workers.runtime import remote
from tests.distributed.helpers import assert_identical, settings


# (1 << 30) rays never arrive: with HOLD, every step with rays waits the whole 20 ms first;
# with SEND, every parcel waits (a minute) until its shard has nothing left to do, and the
# passes complete only if such a shard always lets them go.
# EMIT_RAYS 1: every wavefront iteration that sends anything sends it at once, with a
# share of its passes' weight (the passes still complete exactly once: the render ends).
@pytest.mark.parametrize("knobs", [
    {"HOLD_RAYS": 0, "HOLD_S": 0.0, "SEND_RAYS": 0, "SEND_S": 0.0, "EMIT_RAYS": 0},
    {"HOLD_RAYS": 1 << 30, "HOLD_S": 0.02},
    {"SEND_RAYS": 1 << 30, "SEND_S": 60.0},
    {"EMIT_RAYS": 1, "SEND_RAYS": 0},
    {"EMIT_RAYS": 1, "SEND_RAYS": 1 << 30, "SEND_S": 60.0},
], ids=["nothing_waits", "steps_wait", "parcels_wait_until_idle", "every_iteration_sends",
        "every_iteration_sends_parcels_wait"])
def test_holding_rays_or_parcels_keeps_exact_equal_to_reference(ray_local, scenes, references,
                                                                tmp_path, monkeypatch, knobs):
    for name, value in knobs.items():
        monkeypatch.setattr(remote, name, value)
    result = render(scenes["forest"], settings(3))
    assert_identical(tmp_path, f"forest_{'_'.join(map(str, knobs.values()))}", result,
                     references["forest"])
