"""Input limits: radiometry whose image would overflow float32, quad lights without area
and directional lights without a direction are refused with a SceneError naming the
field, from the model and from a scene file."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from nprt.scene.errors import SceneError
from nprt.scene.io import load_scene
from nprt.scene.model import (
    MAX_RADIOMETRY,
    Camera,
    DirectionalLight,
    Environment,
    Instance,
    Material,
    PointLight,
    QuadLight,
    Scene,
)
from nprt.scene.transform import similarity, transform_scene
from tests.scene._util import rich_scene, tetra


def _with(**changes):
    return dataclasses.replace(rich_scene(), **changes)


OVERFLOWS = {
    "quad_lights[0].radiance": lambda: _with(
        quad_lights=(QuadLight((0, 5, 0), (1, 0, 0), (0, 0, 1), (1.0, 1e308, 1.0)),)),
    "point_lights[0].intensity": lambda: _with(
        point_lights=(PointLight((1, 2, 3), (1e308, 0.0, 0.0)),)),
    "directional_lights[0].irradiance": lambda: _with(
        directional_lights=(DirectionalLight((0, -1, 0), (0.0, 0.0, 1e31)),)),
    "environment.radiance": lambda: _with(environment=Environment(radiance=(1e308,) * 3)),
    "environment.zenith": lambda: _with(
        environment=Environment("sky", zenith=(3e38, 0.0, 0.0), horizon=(1, 1, 1))),
    "materials[1] ('lamp').emission": lambda: _with(
        materials=(rich_scene().materials[0], Material("lamp", emission=(3e38, 3e38, 3e38)))),
}


@pytest.mark.parametrize("field", list(OVERFLOWS))
def test_radiometry_that_would_overflow_float32_is_refused_naming_the_field(field):
    with pytest.raises(SceneError, match="would overflow float32") as info:
        OVERFLOWS[field]()
    assert str(info.value).startswith(field), str(info.value)


def test_radiometry_up_to_the_limit_is_accepted():
    _with(environment=Environment(radiance=(MAX_RADIOMETRY,) * 3))
    _with(quad_lights=(QuadLight((0, 5, 0), (1, 0, 0), (0, 0, 1), (MAX_RADIOMETRY, 0, 0)),))


def test_point_light_limit_follows_the_scene_size():
    # Intensity is W/sr: a scene scaled by s needs s^2 times the intensity for the same
    # image, so the limit is on intensity over the scene's size squared, and a scene is
    # accepted or refused whatever its scale.
    def small(intensity):
        return Scene((tetra(),), (Instance(0, np.eye(4)),),
                     point_lights=(PointLight((1, 2, 3), (intensity,) * 3),))

    bright = small(1e29)  # the tetra's size is sqrt(3): 1e29 / 3 < 1e30
    for s in (1e-6, 1e6):
        moved = transform_scene(bright, similarity(scale=s))
        assert moved.point_lights[0].intensity[0] == pytest.approx(1e29 * s * s)
    for s in (1e-6, 1.0, 1e6):
        with pytest.raises(SceneError, match=r"point_lights\[0\]\.intensity"):
            transform_scene(small(1e32), similarity(scale=s))


@pytest.mark.parametrize("edges", [((1, 0, 0), (2, 0, 0)), ((0, 0, 0), (0, 0, 1)),
                                   ((1, 1e-14, 0), (1, 0, 0))],
                         ids=["parallel", "zero_edge", "nearly_parallel"])
def test_zero_area_quad_light_is_refused(edges):
    with pytest.raises(SceneError, match=r"quad_lights\[0\]: zero area"):
        _with(quad_lights=(QuadLight((0, 5, 0), *edges, (1.0, 1.0, 1.0)),))


@pytest.mark.parametrize("direction", [(0.0, 0.0, 0.0), (1e-200, 0.0, 0.0)],
                         ids=["zero", "underflows"])
def test_zero_length_light_direction_is_refused(direction):
    with pytest.raises(SceneError, match=r"directional_lights\[0\]\.direction: zero length"):
        _with(directional_lights=(DirectionalLight(direction, (1.0, 1.0, 1.0)),))


def test_camera_near_must_be_a_distance():
    with pytest.raises(SceneError, match="camera.near"):
        _with(camera=Camera((1, 2, 3), (0, 0, 0), near=float("nan")))
    with pytest.raises(SceneError, match="camera.near"):
        _with(camera=Camera((1, 2, 3), (0, 0, 0), near=-1.0))


def test_scene_file_with_an_overflowing_light_names_the_file_and_the_field(tmp_path):
    doc = {"meshes": [{"name": "tri", "vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]],
                       "faces": [[0, 1, 2]]}],
           "instances": [{"mesh": "tri"}],
           "lights": {"points": [{"position": [0, 0, 2], "intensity": [1e308, 1, 1]}]}}
    path = tmp_path / "bright.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(SceneError) as info:
        load_scene(path)
    msg = str(info.value)
    assert str(path) in msg and "point_lights[0].intensity" in msg and "overflow" in msg, msg


def test_accepted_scenes_render_finite_images():
    # The limits keep every sample of a scene at the edge finite in float32.
    from nprt.workers.render import render
    from nprt.workers.settings import RenderSettings

    scene = _with(environment=Environment(radiance=(MAX_RADIOMETRY,) * 3),
                  materials=(rich_scene().materials[0],
                             Material("lamp", emission=(MAX_RADIOMETRY,) * 3)))
    img = render(scene, RenderSettings(width=16, height=16, spp=2, bounces=3)).film.image()
    assert np.isfinite(img).all() and img.max() > 1e29
