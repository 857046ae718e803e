"""`byte_slack`, the placement's memory-for-balance knob, as a job setting: validated, the
same after a trip through the gRPC message and the CLI, part of what decides a pool, and
what the placement's partition uses."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from nprt.scene.demos import make_demo
from nprt.scene.partition import BYTE_SLACK
from nprt.service.cli import build_parser, settings_from_args
from nprt.service.grpc_convert import settings_from_pb, settings_to_pb
from nprt.workers.runtime.placement import plan_placement
from nprt.workers.runtime.pool import pool_key
from nprt.workers.settings import RenderSettings


@pytest.mark.parametrize("bad", [0.5, 0.0, -2.0, 17.0, float("nan"), float("inf")])
def test_a_byte_slack_out_of_range_is_refused_naming_the_field(bad):
    with pytest.raises(ValidationError, match="byte_slack"):
        RenderSettings(byte_slack=bad)


@pytest.mark.parametrize("slack", [BYTE_SLACK, 1.0, 1.3, 2.75])
def test_byte_slack_survives_the_grpc_message(slack):
    s = RenderSettings(shards=8, byte_slack=slack)
    assert settings_from_pb(settings_to_pb(s.model_dump())) == s


def test_the_cli_flag_sets_it_and_its_default_is_the_partitions():
    parse = build_parser().parse_args
    assert settings_from_args(parse(["render", "city"])).byte_slack == BYTE_SLACK
    got = settings_from_args(parse(["render", "city", "--shards", "8", "--byte-slack", "1.5"]))
    assert got.byte_slack == 1.5


def test_the_placement_caps_shards_by_it_and_a_pool_is_keyed_on_it():
    # city at its default size: a dozen meshes alike in bytes, so at K = 8 the default cap
    # leaves a shard room for about one and a half of them (its estimate is 1.36x the mean
    # on the busiest shard; 1.02x at 2.0).
    scene = make_demo("city", "default")
    tight, wide = (RenderSettings(shards=8, byte_slack=x) for x in (BYTE_SLACK, 2.0))
    a, b = plan_placement(scene, tight).partition, plan_placement(scene, wide).partition
    assert a.bytes_only_max == b.bytes_only_max
    for p, slack in ((a, BYTE_SLACK), (b, 2.0)):
        assert p.byte_cap == max(int(slack * p.bytes_only_max),
                                 max(m.nbytes for m in scene.meshes))
        assert p.max_shard_bytes <= p.byte_cap
    imbalance = [p.shard_work.max() / p.shard_work.mean() for p in (a, b)]
    assert imbalance[1] < 1.1 < 1.3 < imbalance[0]
    assert pool_key(scene, tight) != pool_key(scene, wide)
