"""A shard that holds its wavefront thread for more rays (nprt.workers.runtime.remote,
HOLD_RAYS / HOLD_S) only groups rays into fewer steps: exact mode still equals the
reference bit for bit, whether no step waits or every step with rays does."""

from __future__ import annotations

import pytest

from nprt.workers.render import render
from nprt.workers.runtime import remote
from tests.distributed.helpers import assert_identical, settings


@pytest.mark.parametrize("hold", [(0, 0.0), (1 << 30, 0.02)], ids=["no_hold", "always_hold"])
def test_holding_for_rays_keeps_exact_equal_to_reference(ray_local, scenes, references,
                                                         tmp_path, monkeypatch, hold):
    # (1 << 30) rays never arrive: every step with rays waits the whole 20 ms first.
    monkeypatch.setattr(remote, "HOLD_RAYS", hold[0])
    monkeypatch.setattr(remote, "HOLD_S", hold[1])
    result = render(scenes["forest"], settings(3))
    assert_identical(tmp_path, f"forest_hold{hold[0]}", result, references["forest"])
