"""Bad render settings are refused up front with one error that names the field."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from nprt.workers.settings import SPP_PER_PASS, RenderSettings


@pytest.mark.parametrize("field,value", [
    ("width", 0), ("height", 0), ("spp", 0), ("width", -3), ("spp", -1), ("tile_size", 0),
    ("spp_per_pass", 0), ("shadow_rays", -1), ("bounces", -1), ("width", 10**6),
])
def test_out_of_range_setting_is_refused_naming_the_field(field, value):
    with pytest.raises(ValueError) as info:  # pydantic's ValidationError is a ValueError
        RenderSettings(**{field: value})
    err = info.value
    assert isinstance(err, ValidationError)
    assert err.error_count() == 1, err.errors()
    assert err.errors()[0]["loc"] == (field,)
    assert field in str(err) and str(value) in str(err), str(err)


def test_unknown_setting_is_refused_naming_it():
    with pytest.raises(ValidationError) as info:
        RenderSettings(samples=4)
    assert info.value.error_count() == 1 and "samples" in str(info.value)


def test_zero_width_is_refused_before_any_rendering_starts():
    # The error must come from the settings model, not from an empty film deep in a pass.
    from nprt.workers.render import render

    with pytest.raises(ValidationError, match="width"):
        render(None, RenderSettings(width=0))  # scene is never looked at


def test_defaults_are_valid_and_frozen():
    s = RenderSettings()
    assert s.width >= 1 and s.spp >= 1
    with pytest.raises(ValidationError):
        s.spp = 0


def test_a_pass_never_holds_more_samples_than_the_job():
    """spp_per_pass above spp renders the same passes (one chunk of spp samples); the
    settings then say so, so a job's record and its memory estimate count what it renders."""
    from nprt.workers.passes import count_passes

    s = RenderSettings(width=100, height=70, spp=4)
    assert s.spp_per_pass == 4 and s == RenderSettings(width=100, height=70, spp=4,
                                                       spp_per_pass=4)
    assert count_passes(s) == count_passes(RenderSettings(width=100, height=70, spp=4,
                                                          spp_per_pass=1000))
    assert RenderSettings(spp=64).spp_per_pass == SPP_PER_PASS
