"""Keyframed JSON animations: sampling, frames sharing meshes, and errors naming the key."""

from __future__ import annotations

import json

import numpy as np
import pytest

from nprt.scene.animation import frame_range, sample_rotation
from nprt.scene.errors import SceneError
from nprt.scene.io import load_scene, save_scene
from nprt.workers.frames import frame_path

TRI = {"name": "tri", "vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "faces": [[0, 1, 2]]}


def _load(tmp_path, animation: dict, **extra):
    doc = {"meshes": [TRI], "instances": [{"mesh": "tri"}, {"mesh": "tri", "translate": [3, 0, 0]}],
           "lights": {"directionals": [{"direction": [0, -1, 0], "irradiance": [1, 1, 1]}],
                      "points": [{"position": [0, 5, 0], "intensity": [2, 2, 2]}]},
           "animation": animation, **extra}
    (tmp_path / "s.json").write_text(json.dumps(doc))
    return load_scene(tmp_path / "s.json")


def test_linear_keys_interpolate_and_frames_share_meshes(tmp_path):
    scene = _load(tmp_path, {"frames": 5, "instances": {"1": [
        {"frame": 0, "translate": [3, 0, 0]},
        {"frame": 4, "translate": [7, 0, 0], "rotate_deg": [0, 90, 0], "scale": 2}]},
        "lights": {"directionals": {"0": [{"frame": 0}, {"frame": 4, "direction": [1, -1, 0]}]},
                   "points": {"0": [{"frame": 2, "intensity": [4, 4, 4]}]}}})
    assert scene.frames == 5 and scene.summary()["frames"] == 5
    for f in range(5):
        at = scene.at_frame(f)
        assert at.meshes is scene.meshes and at.materials is scene.materials
        np.testing.assert_allclose(at.instance_transform[1][:3, 3], [3 + f, 0, 0])
        np.testing.assert_array_equal(at.instance_transform[0], np.eye(4))  # no track
        assert at.directional_lights[0].direction == pytest.approx((f / 4, -1, 0))
        assert at.point_lights[0].intensity == (4, 4, 4)  # one key: held on every frame
        assert at.point_lights[0].position == (0, 5, 0)  # not keyed: the light's own
    mid = scene.at_frame(2).instance_transform[1][:3, :3]
    c, s_ = np.cos(np.radians(45)), np.sin(np.radians(45))
    np.testing.assert_allclose(mid, 1.5 * np.array([[c, 0, s_], [0, 1, 0], [-s_, 0, c]]),
                               atol=1e-12)
    np.testing.assert_array_equal(scene.instance_transform, scene.at_frame(0).instance_transform)


def test_step_holds_the_earlier_key(tmp_path):
    scene = _load(tmp_path, {"frames": 4, "interpolation": "step", "instances": {"1": [
        {"frame": 0, "translate": [0, 0, 0]}, {"frame": 2, "translate": [10, 0, 0]}]}})
    xs = [scene.at_frame(f).instance_transform[1][0, 3] for f in range(4)]
    assert xs == [0, 0, 10, 10]


def test_slerp_takes_the_shorter_arc():
    q0 = np.array([1.0, 0, 0, 0])
    q1 = -np.array([np.cos(np.pi / 4), 0, np.sin(np.pi / 4), 0])  # 90 deg about y, negated
    q = sample_rotation([0, 1], [q0, q1], [0.5])[0]
    assert abs(q[0]) == pytest.approx(np.cos(np.pi / 8))


@pytest.mark.parametrize("animation, message", [
    ({"frames": 3, "instances": {"1": [{"frame": 3, "translate": [0, 0, 0]}]}},
     "animation.instances[1]: key at frame 3 is past the last frame (2)"),
    ({"frames": 3, "instances": {"1": [{"frame": 1}, {"frame": 1}]}},
     "key frames must be strictly increasing"),
    ({"frames": 3, "instances": {"5": [{"frame": 0}]}}, "animation.instances[5]: no such instance"),
    ({"frames": 3, "lights": {"points": {"0": [{"frame": 0, "direction": [1, 0, 0]}]}}},
     "'direction' is not a field of this light"),
    ({"frames": 3, "lights": {"directionals": {"0": [{"frame": 0}, {"frame": 2, "direction":
                                                                     [0, 0, 0]}]}}},
     "directional_lights[0].direction: zero length"),
    ({"frames": 3, "instances": {"1": [{"frame": 1, "transform": [[1, 1, 0, 0], [0, 1, 0, 0],
                                                                  [0, 0, 1, 0], [0, 0, 0, 1]]}]}},
     "has shear"),
    ({"frames": 0}, "animation.frames: Input should be greater than or equal to 1"),
])
def test_bad_animations_name_the_key(tmp_path, animation, message):
    with pytest.raises(SceneError, match="s.json") as e:
        _load(tmp_path, animation)
    assert message in str(e.value)


def test_frames_out_of_range(tmp_path):
    scene = _load(tmp_path, {"frames": 2,
                             "instances": {"1": [{"frame": 1, "translate": [1, 1, 1]}]}})
    with pytest.raises(SceneError, match="frame 2 out of range.*0 to 1"):
        scene.at_frame(2)


ROUND_TRIP = {"frames": 6, "instances": {"1": [
    {"frame": 0, "translate": [3, 0, 0]},
    {"frame": 5, "translate": [7, 0.3, 0], "rotate_deg": [10, 77, 0], "scale": 1.7}]},
    "lights": {"directionals": {"0": [{"frame": 0}, {"frame": 5, "direction": [1, -1, 0.3]}]},
               "points": {"0": [{"frame": 1, "intensity": [4, 4, 4]},
                                {"frame": 4, "position": [0.1, 5, 2]}]}}}


@pytest.mark.parametrize("instance_file", [False, True], ids=["listed", "npz"])
def test_save_writes_the_animation_and_every_frame_loads_back_bit_for_bit(tmp_path,
                                                                          instance_file):
    """The scene cache stores animated demos with save_scene: what comes back, whole or as
    metadata, must be the same frames to the last bit (exact renders are compared)."""
    from nprt.scene.meta import load_scene_meta

    scene = _load(tmp_path, ROUND_TRIP)
    out = save_scene(scene.at_frame(3), tmp_path / "out" / "s.json", instance_file)
    for back in (load_scene(out), load_scene_meta(out)):
        assert back.frames == scene.frames
        for f in range(scene.frames):
            want, got = scene.at_frame(f), back.at_frame(f)
            np.testing.assert_array_equal(got.instance_transform, want.instance_transform)
            assert (got.quad_lights, got.point_lights, got.directional_lights) == \
                (want.quad_lights, want.point_lights, want.directional_lights)
    assert not np.array_equal(scene.at_frame(2).instance_transform,
                              scene.at_frame(3).instance_transform)  # it moves


def test_frame_range_and_frame_path():
    assert frame_range("2:5", 8) == range(2, 6)
    assert frame_range("3", 8) == range(3, 4)
    assert frame_range(":", 8) == range(0, 8)
    for bad in ("5:2", "0:8", "x"):
        with pytest.raises(SceneError, match=f"frames {bad!r}"):
            frame_range(bad, 8)
    assert frame_path("out_####.png", 7) == "out_0007.png"
    assert frame_path("a#/b_##.exr", 12) == "a#/b_12.exr"
    assert frame_path("out.png", 3) == "out_0003.png"


def test_trs_matrices_match_trimesh_and_split_trs_inverts_them():
    from trimesh import transformations as tf

    from nprt.scene.animation import split_trs, trs_matrices

    rng = np.random.default_rng(0)
    q = tf.random_quaternion(rand=rng.random(3))
    t, s = rng.normal(size=3), rng.uniform(0.5, 2.0, 3)
    m = trs_matrices(t[None], q[None], s[None])[0]
    np.testing.assert_allclose(m, tf.translation_matrix(t) @ tf.quaternion_matrix(q)
                               @ np.diag([*s, 1.0]), atol=1e-12)
    t2, q2, s2 = split_trs(m, "here")
    np.testing.assert_allclose(trs_matrices(t2[None], q2[None], s2[None])[0], m, atol=1e-12)
