"""Confinement: with a root (an upload), no path a scene names can read a file outside it,
whether absolute, by `..` or through a symlink; without one (the CLI), local paths work."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import trimesh

from nprt.scene.errors import SceneError, UnsafePath
from nprt.scene.gltf import load_gltf
from nprt.scene.io import load_any, load_scene
from tests.scene._util import recording_opens

TRI = {"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "faces": [[0, 1, 2]]}


@pytest.fixture
def layout(tmp_path):
    """upload/ (the root) and, beside it, outside/ holding a valid mesh and texture."""
    root, outside = tmp_path / "upload", tmp_path / "outside"
    root.mkdir()
    outside.mkdir()
    (outside / "secret.ply").write_bytes(
        trimesh.creation.icosphere(subdivisions=1).export(file_type="ply"))
    np.save(outside / "secret.npy", np.full((2, 2, 3), 0.5, np.float32))
    (root / "ball.ply").write_bytes(trimesh.creation.box().export(file_type="ply"))
    np.save(root / "tex.npy", np.full((2, 2, 3), 0.25, np.float32))
    return root, outside


def _scene_json(root, mesh_path="ball.ply", texture="tex.npy", name="scene.json"):
    doc = {"materials": [{"name": "m", "texture": texture}],
           "meshes": [{"name": "ball", "path": mesh_path, "material": "m"}],
           "instances": [{"mesh": "ball"}]}
    path = root / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc))
    return path


def _refused(entry, root, outside, ref: str = "") -> str:
    """Load confined to root: UnsafePath, and no file under `outside` was opened. The
    message shows no server path besides `ref`, the one the scene itself wrote."""
    with recording_opens() as opened, pytest.raises(UnsafePath) as info:
        load_any(str(entry), root=root)
    assert not [p for p in opened if p.startswith(str(outside.resolve()))]
    message = str(info.value)
    assert str(root.parent) not in message.replace(ref, "")
    return message


@pytest.mark.parametrize("field", ["mesh", "texture"])
def test_absolute_path_is_refused_and_not_read(layout, field):
    root, outside = layout
    target = str(outside / ("secret.ply" if field == "mesh" else "secret.npy"))
    kwargs = {"mesh_path": target} if field == "mesh" else {"texture": target}
    message = _refused(_scene_json(root, **kwargs), root, outside, target)
    assert f"path {target!r} is absolute" in message and "scene.json" in message
    assert ("meshes[0] ('ball')" if field == "mesh" else "materials[0] ('m')") in message


@pytest.mark.parametrize("field", ["mesh", "texture"])
def test_dotdot_escape_is_refused_and_not_read(layout, field):
    root, outside = layout
    ref = "sub/../../outside/" + ("secret.ply" if field == "mesh" else "secret.npy")
    kwargs = {"mesh_path": ref} if field == "mesh" else {"texture": ref}
    message = _refused(_scene_json(root, **kwargs), root, outside)
    assert f"path {ref!r} leaves the upload" in message


@pytest.mark.parametrize("field", ["mesh", "texture"])
def test_symlink_leaving_the_root_is_refused_and_not_read(layout, field):
    root, outside = layout
    name = "link.ply" if field == "mesh" else "link.npy"
    os.symlink(outside / ("secret.ply" if field == "mesh" else "secret.npy"), root / name)
    kwargs = {"mesh_path": name} if field == "mesh" else {"texture": name}
    message = _refused(_scene_json(root, **kwargs), root, outside)
    assert f"path {name!r} leaves the upload through a symlink" in message


def test_symlinked_directory_leaving_the_root_is_refused(layout):
    root, outside = layout
    os.symlink(outside, root / "meshes")
    _refused(_scene_json(root, mesh_path="meshes/secret.ply"), root, outside)


def test_obj_mtl_and_texture_outside_the_root_are_refused(layout):
    root, outside = layout
    (outside / "evil.mtl").write_text("newmtl m\nKd 1 0 0\n")
    obj = "mtllib ../outside/evil.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl m\nf 1 2 3\n"
    (root / "tri.obj").write_text(obj)
    message = _refused(_scene_json(root, mesh_path="tri.obj"), root, outside)
    assert "'../outside/evil.mtl' leaves the upload" in message


def test_ply_texture_file_outside_the_root_is_refused(layout):
    root, outside = layout
    ply = (root / "ball.ply").read_bytes().replace(
        b"element vertex", b"comment TextureFile ../outside/secret.npy\nelement vertex", 1)
    (root / "ball.ply").write_bytes(ply)
    _refused(_scene_json(root), root, outside)


@pytest.mark.parametrize("uri", ["../outside/secret.bin", "/etc/hostname", "%s"])
def test_gltf_external_buffer_outside_the_root_is_refused(layout, uri):
    root, outside = layout
    box = trimesh.creation.box()
    files = box.export(file_type="gltf")  # {"model.gltf": ..., "gltf_buffer_0.bin": ...}
    doc = json.loads(files["model.gltf"])
    (outside / "secret.bin").write_bytes(files[doc["buffers"][0]["uri"]])
    uri = uri if uri != "%s" else str(outside / "secret.bin")
    doc["buffers"][0]["uri"] = uri
    (root / "box.gltf").write_text(json.dumps(doc))
    message = _refused(root / "box.gltf", root, outside, uri)
    assert "box.gltf" in message and "referenced file path" in message


def test_dotdot_and_symlinks_that_stay_inside_the_root_load(layout):
    root, _ = layout
    (root / "meshes").mkdir()
    os.symlink(root / "ball.ply", root / "meshes" / "alias.ply")
    entry = _scene_json(root, mesh_path="../meshes/alias.ply", texture="../tex.npy",
                        name="sub/scene.json")
    scene = load_any(str(entry), root=root)
    assert len(scene.meshes[0].faces) == 12
    np.testing.assert_allclose(scene.materials[0].texture, 0.25)


def test_without_a_root_local_absolute_paths_are_read(layout):
    root, outside = layout  # the CLI: the user's own files, wherever they are
    entry = _scene_json(root, mesh_path=str(outside / "secret.ply"),
                        texture=str(outside / "secret.npy"))
    with recording_opens() as opened:
        scene = load_scene(entry)
    assert str((outside / "secret.ply").resolve()) in opened  # the audit hook sees reads
    assert len(scene.meshes[0].faces) == 80


def test_gltf_with_external_buffer_inside_the_root_loads(layout):
    root, _ = layout
    for name, data in trimesh.creation.box().export(file_type="gltf").items():
        (root / name).write_bytes(data)
    assert len(load_gltf(root / "model.gltf", root=root).meshes[0].faces) == 12


@pytest.mark.parametrize("kind", ["fifo", "directory", "loop", "dangling"])
def test_unreadable_kinds_of_file_are_named_not_called_missing(tmp_path, kind):
    target = tmp_path / "rock.ply"
    if kind == "fifo":
        os.mkfifo(target)
    elif kind == "directory":
        target.mkdir()
    elif kind == "loop":
        os.symlink(tmp_path / "other.ply", target)
        os.symlink(target, tmp_path / "other.ply")
    else:
        os.symlink(tmp_path / "gone.ply", target)
    entry = _scene_json(tmp_path, mesh_path="rock.ply", texture=None)
    with pytest.raises(SceneError) as info:
        load_scene(entry)
    expected = {"fifo": "mesh file is a FIFO, not a regular file",
                "directory": "mesh file is a directory, not a regular file",
                "loop": "mesh file is a symlink loop", "dangling": "is a dangling symlink"}
    assert expected[kind] in str(info.value) and "rock.ply" in str(info.value)
    assert "not found" not in str(info.value)
