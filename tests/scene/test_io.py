"""JSON scene files: exact round trips, mesh files, TRS instances, degenerate triangles."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from nprt.scene.demos import make_demo
from nprt.scene.io import load_any, load_scene, save_scene
from nprt.scene.model import Instance, Material, Scene
from tests.scene._util import assert_scenes_equal, rich_scene, tetra, translate


def test_json_round_trip_preserves_geometry_and_transforms(tmp_path):
    scene = rich_scene()
    save_scene(scene, tmp_path / "rich.json")
    assert_scenes_equal(scene, load_scene(tmp_path / "rich.json"))


def test_json_round_trip_of_demo_scene(tmp_path):
    scene = make_demo("forest", "tiny", seed=3)
    save_scene(scene, tmp_path / "sub" / "forest.json")
    assert_scenes_equal(scene, load_scene(tmp_path / "sub" / "forest.json"))


def test_saved_meshes_are_ply_files_referenced_relatively(tmp_path):
    save_scene(rich_scene(), tmp_path / "a.json")
    doc = json.loads((tmp_path / "a.json").read_text())
    paths = [m["path"] for m in doc["meshes"]]
    assert all(p.endswith(".ply") and "/" not in p for p in paths)
    assert all((tmp_path / p).is_file() for p in paths)
    moved = tmp_path / "moved"
    moved.mkdir()
    for f in tmp_path.glob("a.*"):
        f.rename(moved / f.name)
    assert len(load_scene(moved / "a.json").meshes) == 2


def test_round_trip_with_repeated_mesh_names_references_by_index(tmp_path):
    scene = Scene((tetra("same"), tetra("same", normals=True)),
                  (Instance(1, np.eye(4)), Instance(0, translate(2.0))))
    save_scene(scene, tmp_path / "dup.json")
    doc = json.loads((tmp_path / "dup.json").read_text())
    assert [i["mesh"] for i in doc["instances"]] == [1, 0]
    assert_scenes_equal(scene, load_scene(tmp_path / "dup.json"))


def test_instance_translate_rotate_scale_compose_as_t_r_s(tmp_path):
    doc = {
        "meshes": [{"name": "tri", "vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]],
                    "faces": [[0, 1, 2]]}],
        "instances": [{"mesh": "tri", "translate": [1, 2, 3], "rotate_deg": [0, 90, 0],
                       "scale": [2, 3, 4]}, {"mesh": 0}],
    }
    (tmp_path / "s.json").write_text(json.dumps(doc))
    scene = load_scene(tmp_path / "s.json")
    xf = scene.instances[0].transform
    # x axis (scaled by 2) turns to -z under a +90 degree yaw; then translate.
    np.testing.assert_allclose(xf @ [1, 0, 0, 1], [1, 2, 1, 1], atol=1e-12)
    np.testing.assert_allclose(xf @ [0, 1, 0, 1], [1, 5, 3, 1], atol=1e-12)
    np.testing.assert_allclose(xf @ [0, 0, 1, 1], [5, 2, 3, 1], atol=1e-12)
    assert np.array_equal(scene.instances[1].transform, np.eye(4))


def test_mesh_file_paths_resolve_relative_to_scene_file(tmp_path):
    (tmp_path / "meshes").mkdir()
    trimesh.creation.box().export(tmp_path / "meshes" / "box.obj")
    doc = {"materials": [{"name": "red", "albedo": [0.9, 0.1, 0.1]}],
           "meshes": [{"name": "box", "path": "meshes/box.obj", "material": "red"}],
           "instances": [{"mesh": "box"}]}
    (tmp_path / "s.json").write_text(json.dumps(doc))
    scene = load_scene(tmp_path / "s.json")
    assert len(scene.meshes[0].faces) == 12
    assert scene.materials[scene.meshes[0].material].albedo == (0.9, 0.1, 0.1)


def test_degenerate_triangles_are_dropped_and_counted(tmp_path):
    doc = {"meshes": [{"name": "m",
                       "vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]],
                       "faces": [[0, 1, 2], [0, 0, 1], [0, 1, 3], [1, 2, 0]]}],
           "instances": [{"mesh": "m"}]}
    (tmp_path / "s.json").write_text(json.dumps(doc))
    mesh = load_scene(tmp_path / "s.json").meshes[0]
    assert mesh.dropped_degenerate == 2  # a repeated corner, and three collinear points
    assert mesh.faces.tolist() == [[0, 1, 2], [1, 2, 0]]


def test_degenerate_triangles_in_mesh_files_are_dropped(tmp_path):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]], dtype=np.float64)
    f = np.array([[0, 1, 2], [0, 1, 3], [2, 2, 2]])
    trimesh.Trimesh(v, f, process=False).export(tmp_path / "m.ply")
    doc = {"meshes": [{"name": "m", "path": "m.ply"}], "instances": [{"mesh": "m"}]}
    (tmp_path / "s.json").write_text(json.dumps(doc))
    mesh = load_scene(tmp_path / "s.json").meshes[0]
    assert (mesh.dropped_degenerate, len(mesh.faces)) == (2, 1)


def test_load_any_accepts_demo_names_with_sizes():
    assert load_any("city:tiny").name == "city-tiny"
    assert load_any("sculpture", size="tiny").name == "sculpture-tiny"


def test_load_any_accepts_json_glb_and_mesh_files(tmp_path):
    save_scene(rich_scene(), tmp_path / "r.json")
    assert load_any(tmp_path / "r.json").name == "rich"
    assert load_any(str(tmp_path / "r.json")).name == "rich"
    box = trimesh.creation.box()
    trimesh.Scene(box).export(tmp_path / "b.glb")
    box.export(tmp_path / "b.ply")
    for path in (tmp_path / "b.glb", tmp_path / "b.ply"):
        scene = load_any(path)
        assert (len(scene.meshes), len(scene.instances)) == (1, 1)
        assert scene.environment.kind == "sky"


@pytest.mark.parametrize("albedo", [(1.2, 0.5, 0.5), (-0.1, 0.5, 0.5)])
def test_save_refuses_what_load_would_reject(tmp_path, albedo):
    from nprt.scene.errors import SceneError

    bad = Scene((tetra(),), (Instance(0, np.eye(4)),), (Material("m", albedo),))
    with pytest.raises(SceneError, match=r"materials\[0\]\.albedo\[0\]"):
        save_scene(bad, tmp_path / "bad.json")
