"""The accuracy target as a setting: defaults, hand-set bands, clear errors, and the same
value after a trip through the gRPC message."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from nprt.service.grpc_convert import settings_from_pb, settings_to_pb
from nprt.workers.settings import ProxySettings, RenderSettings


def test_the_default_is_a_40_db_target_and_hand_set_bands_replace_it():
    assert ProxySettings().accuracy == 40.0
    assert ProxySettings(band=0.2).accuracy is None  # the bands as given, for every proxy
    assert ProxySettings(accuracy="35dB", band=0.2).accuracy == 35.0  # both: the target


def test_a_bad_accuracy_is_refused_naming_the_value():
    with pytest.raises(ValidationError, match="got 'fast'"):
        ProxySettings(accuracy="fast")
    with pytest.raises(ValidationError, match="150"):
        ProxySettings(accuracy=150)


@pytest.mark.parametrize("knobs", [ProxySettings(), ProxySettings(accuracy="exact", check=True),
                                   ProxySettings(band=0.2, shadow_band=0.1),
                                   ProxySettings(accuracy=33.5, internal_margin=1.0,
                                                 internal_ambiguous="trust")])
def test_accuracy_and_internal_knobs_survive_the_grpc_message(knobs):
    s = RenderSettings(shards=2, mode="proxy", proxy=knobs)
    assert settings_from_pb(settings_to_pb(s.model_dump())).proxy == knobs
