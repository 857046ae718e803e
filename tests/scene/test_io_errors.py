"""Bad input gives one SceneError whose message names the problem and where it is."""

from __future__ import annotations

import json

import pytest

from nprt.scene.errors import SceneError
from nprt.scene.io import load_any, load_scene

TRI = {"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "faces": [[0, 1, 2]]}


def _load(tmp_path, doc, files: dict | None = None) -> SceneError:
    for name, text in (files or {}).items():
        (tmp_path / name).write_text(text)
    path = tmp_path / "scene.json"
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    with pytest.raises(SceneError) as info:
        load_scene(path)
    err = info.value
    assert err.__cause__ is None and err.__suppress_context__  # no chained library traceback
    assert str(path) in str(err) or "scene.json" in str(err)
    return err


def _scene(mesh: dict | None = None, instance: dict | None = None, **top) -> dict:
    return {"meshes": [{"name": "tree", **(TRI if mesh is None else mesh)}],
            "instances": [{"mesh": "tree", **(instance or {})}], **top}


def test_malformed_json_names_line_and_column(tmp_path):
    err = _load(tmp_path, '{\n  "meshes": [\n    {"name": "a",,}\n  ]\n}')
    assert "malformed JSON at line 3, column" in str(err)


def test_missing_mesh_file_names_mesh_and_path(tmp_path):
    err = _load(tmp_path, _scene({"path": "leaves/missing.ply"}))
    assert "meshes[0] ('tree')" in str(err)
    assert "mesh file not found" in str(err) and "missing.ply" in str(err)


def test_unreadable_mesh_file_names_the_file(tmp_path):
    err = _load(tmp_path, _scene({"path": "junk.ply"}), {"junk.ply": "ply\nthis is not ply"})
    assert "could not read mesh file" in str(err) and "junk.ply" in str(err)


def test_nan_inline_vertex_names_the_json_field(tmp_path):
    mesh = {"vertices": [[0, 0, 0], [1, 0, 0], [0, float("nan"), 0]], "faces": [[0, 1, 2]]}
    err = _load(tmp_path, _scene(mesh))
    assert "meshes[0].vertices[2][1]" in str(err) and "finite" in str(err)


def test_nan_vertex_in_mesh_file_names_mesh_and_vertex(tmp_path):
    obj = "v 0 0 0\nv 1 0 0\nv 0 nan 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n"
    err = _load(tmp_path, _scene({"path": "rock.obj"}), {"rock.obj": obj})
    assert "meshes[0] ('tree')" in str(err)
    assert "vertex 2 is not finite" in str(err)


def test_singular_transform_names_the_instance(tmp_path):
    doc = _scene()
    doc["instances"].append({"mesh": "tree", "scale": [1.0, 0.0, 1.0]})
    err = _load(tmp_path, doc)
    assert "instances[1]" in str(err) and "singular" in str(err)


def test_non_affine_matrix_names_the_instance(tmp_path):
    m = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]
    err = _load(tmp_path, _scene(instance={"transform": m}))
    assert "instances[0]" in str(err) and "not affine" in str(err)


def test_empty_inline_mesh_names_the_mesh(tmp_path):
    err = _load(tmp_path, _scene({"vertices": [], "faces": []}))
    assert "meshes[0] ('tree')" in str(err) and "mesh is empty" in str(err)


def test_empty_mesh_file_names_the_mesh(tmp_path):
    err = _load(tmp_path, _scene({"path": "empty.obj"}), {"empty.obj": "# nothing\n"})
    assert "meshes[0] ('tree')" in str(err) and ("empty" in str(err) or "no triangle" in str(err))


def test_mesh_of_only_degenerate_triangles_is_refused(tmp_path):
    mesh = {"vertices": [[0, 0, 0], [1, 0, 0], [2, 0, 0]], "faces": [[0, 1, 2], [0, 0, 0]]}
    err = _load(tmp_path, _scene(mesh))
    assert "all 2 triangles are degenerate" in str(err)


def test_face_index_out_of_range_names_the_mesh(tmp_path):
    err = _load(tmp_path, _scene({"vertices": TRI["vertices"], "faces": [[0, 1, 7]]}))
    assert "meshes[0] ('tree')" in str(err) and "face index 7 out of range" in str(err)


def test_unknown_mesh_reference_names_the_instance_field(tmp_path):
    err = _load(tmp_path, _scene(instance={"mesh": "oak"}))
    assert "instances[0].mesh: unknown mesh 'oak'" in str(err)


def test_mesh_index_out_of_range_names_the_instance_field(tmp_path):
    err = _load(tmp_path, _scene(instance={"mesh": 3}))
    assert "instances[0].mesh: mesh index 3 out of range (there are 1)" in str(err)


def test_unknown_material_reference_names_the_mesh_field(tmp_path):
    err = _load(tmp_path, _scene({**TRI, "material": "gold"}))
    assert "meshes[0] ('tree').material: unknown material 'gold'" in str(err)


@pytest.mark.parametrize(
    ("patch", "expected"),
    [
        ({"camera": {"fov_deg": 190}}, "camera.fov_deg: Input should be less than 180"),
        ({"camera": {"eye": [0, 5, 0], "target": [0, 0, 0]}}, "camera: 'up' is zero or parall"),
        ({"camera": {"eye": [1, 1, 1], "target": [1, 1, 1]}}, "camera: 'eye' and 'target' coin"),
        ({"materials": [{"name": "m", "albedo": [0.5, 1.5, 0.5]}]}, "materials[0].albedo[1]"),
        ({"lights": {"points": [{"position": [0, 1], "intensity": [1, 1, 1]}]}},
         "lights.points[0].position"),
        ({"instances": []}, "instances: List should have at least 1 item"),
        ({"environment": {"kind": "hdri"}}, "environment.kind"),
        ({"meshes": [{"name": "tree", "pth": "x.ply"}]}, "meshes[0].pth: Extra inputs"),
        ({"meshes": [{"name": "tree"}]}, "meshes[0]: needs a 'path' or both inline"),
        ({"instances": [{"mesh": "tree", "scale": 2, "transform": [[1, 0, 0, 0]] * 4}]},
         "instances[0]: give either 'transform' or translate/rotate_deg/scale"),
    ],
)
def test_schema_errors_name_the_json_field_path(tmp_path, patch, expected):
    err = _load(tmp_path, {**_scene(), **patch})
    assert "invalid scene file" in str(err) and expected in str(err)


def test_top_level_not_an_object_is_reported(tmp_path):
    err = _load(tmp_path, "[1, 2, 3]")
    assert "(top level)" in str(err)


def test_missing_scene_file_is_reported(tmp_path):
    with pytest.raises(SceneError, match="scene file not found"):
        load_scene(tmp_path / "nope.json")


def test_load_any_unknown_name_lists_the_demos():
    with pytest.raises(SceneError, match=r"unknown scene 'jungle'.*forest, city, sculpture"):
        load_any("jungle")


def test_load_any_unknown_demo_size_is_refused():
    with pytest.raises(SceneError, match="unknown size 'huge'"):
        load_any("forest:huge")


def test_corrupt_glb_is_reported(tmp_path):
    (tmp_path / "bad.glb").write_bytes(b"glTF\x02\x00\x00\x00garbage")
    with pytest.raises(SceneError, match=r"bad\.glb: could not read glTF"):
        load_any(tmp_path / "bad.glb")
