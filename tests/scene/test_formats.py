"""Every mesh format trimesh reads loads with its geometry, normals, UVs and material:
ASCII and binary PLY, OBJ with MTL, ASCII and binary STL, glTF with external buffers,
GLB with a texture. Files are written at test time by trimesh."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from PIL import Image
from trimesh.exchange.obj import export_obj
from trimesh.exchange.ply import export_ply
from trimesh.exchange.stl import export_stl, export_stl_ascii

from nprt.scene.io import load_any
from nprt.scene.model import Mesh
from nprt.scene.texture import srgb_to_linear

RNG = np.random.default_rng(5)
TEXELS = (RNG.random((4, 6, 3)) * 255).astype(np.uint8)  # (h, w, 3) sRGB


def _source() -> trimesh.Trimesh:
    ball = trimesh.creation.icosphere(subdivisions=1)
    ball.vertices *= [1.0, 2.0, 0.5]  # not symmetric: a swapped axis would show
    return ball


def _triangles(vertices, faces) -> np.ndarray:
    """(f, 9) float64 triangle corners, rows sorted: equal for equal triangle sets."""
    tri = np.asarray(vertices, np.float64)[np.asarray(faces)].reshape(-1, 9)
    return tri[np.lexsort(tri.T[::-1])]


def _assert_same_geometry(mesh: Mesh, source: trimesh.Trimesh) -> None:
    np.testing.assert_allclose(_triangles(mesh.vertices, mesh.faces),
                               _triangles(source.vertices, source.faces), atol=1e-6)


def _textured(source: trimesh.Trimesh) -> trimesh.Trimesh:
    uv = RNG.random((len(source.vertices), 2))
    material = trimesh.visual.material.SimpleMaterial(
        image=Image.fromarray(TEXELS), diffuse=[255, 255, 255, 255])
    return trimesh.Trimesh(source.vertices, source.faces, process=False,
                           visual=trimesh.visual.TextureVisuals(uv=uv, material=material))


@pytest.mark.parametrize("encoding", ["ascii", "binary"])
def test_ply_loads_with_the_file_normals(tmp_path, encoding):
    source = _source()
    normals = RNG.normal(size=(len(source.vertices), 3)).astype(np.float32)
    tm = trimesh.Trimesh(source.vertices, source.faces, process=False)
    for i, axis in enumerate("xyz"):
        tm.vertex_attributes["n" + axis] = normals[:, i]
    (tmp_path / "ball.ply").write_bytes(export_ply(tm, encoding=encoding, vertex_normal=False))
    mesh = load_any(tmp_path / "ball.ply").meshes[0]
    np.testing.assert_array_equal(mesh.faces, source.faces)
    np.testing.assert_allclose(mesh.vertices, source.vertices, atol=1e-6)
    np.testing.assert_allclose(mesh.normals, normals, atol=1e-6)


@pytest.mark.parametrize("encoding", ["ascii", "binary"])
def test_ply_without_normals_loads(tmp_path, encoding):
    source = _source()
    (tmp_path / "ball.ply").write_bytes(export_ply(source, encoding=encoding,
                                                   vertex_normal=False))
    mesh = load_any(tmp_path / "ball.ply").meshes[0]
    _assert_same_geometry(mesh, source)
    assert mesh.normals is None


def test_obj_loads_with_its_mtl_colour_and_texture(tmp_path):
    source = _textured(_source())
    obj, files = export_obj(source, include_texture=True, return_texture=True,
                            mtl_name="ball.mtl")
    (tmp_path / "ball.obj").write_text(obj)
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    mtl = (tmp_path / "ball.mtl").read_text()
    (tmp_path / "ball.mtl").write_text(
        "\n".join("Kd 0.5 0.25 1.0" if line.startswith("Kd") else line
                  for line in mtl.splitlines()))
    scene = load_any(tmp_path / "ball.obj")
    mesh = scene.meshes[0]
    _assert_same_geometry(mesh, source)
    material = scene.materials[mesh.material]
    np.testing.assert_allclose(material.albedo, [0.5, 0.25, 1.0], atol=1.0 / 255)
    kd = np.array([128, 64, 255]) / 255.0  # the MTL's Kd, as trimesh stores it (uint8)
    np.testing.assert_allclose(material.texture, srgb_to_linear(TEXELS / 255.0) * kd,
                               atol=1e-6)
    assert mesh.uvs is not None and mesh.uvs.shape == (len(mesh.vertices), 2)
    corners = mesh.vertices[mesh.faces].reshape(-1, 3)  # UVs follow their vertices
    expected = {tuple(np.round(v, 5)): tuple(np.round(t, 5)) for v, t in
                zip(source.vertices, source.visual.uv, strict=True)}
    got = mesh.uvs[mesh.faces].reshape(-1, 2)
    for v, t in zip(corners, got, strict=True):
        np.testing.assert_allclose(t, expected[tuple(np.round(v.astype(np.float64), 5))],
                                   atol=1e-5)


def test_obj_without_mtl_keeps_its_normals_and_gets_the_default_material(tmp_path):
    source = _source()
    (tmp_path / "ball.obj").write_text(export_obj(source, include_texture=False,
                                                  include_normals=True))
    scene = load_any(tmp_path / "ball.obj")
    mesh = scene.meshes[0]
    np.testing.assert_array_equal(mesh.faces, source.faces)
    np.testing.assert_allclose(mesh.normals, source.vertex_normals, atol=1e-6)
    assert scene.materials[0].texture is None and scene.materials[0].albedo == (0.8, 0.8, 0.8)


@pytest.mark.parametrize("encoding", ["ascii", "binary"])
def test_stl_loads(tmp_path, encoding):
    source = _source()
    data = export_stl_ascii(source).encode() if encoding == "ascii" else export_stl(source)
    (tmp_path / "ball.stl").write_bytes(data)
    _assert_same_geometry(load_any(tmp_path / "ball.stl").meshes[0], source)


def _write_gltf(folder, source) -> dict:
    files = trimesh.Scene(source).export(file_type="gltf")  # model.gltf + buffer files
    for name, data in files.items():
        (folder / name).write_bytes(data)
    return json.loads(files["model.gltf"])


def test_gltf_with_external_buffers_loads(tmp_path):
    source = _source()
    doc = _write_gltf(tmp_path, source)
    assert all("uri" in b and not b["uri"].startswith("data:") for b in doc["buffers"])
    _assert_same_geometry(load_any(tmp_path / "model.gltf").meshes[0], source)


def test_gltf_with_external_buffers_loads_as_a_scene_mesh(tmp_path):
    source = _source()
    (tmp_path / "meshes").mkdir()
    _write_gltf(tmp_path / "meshes", source)
    scene_doc = {"meshes": [{"name": "ball", "path": "meshes/model.gltf"}],
                 "instances": [{"mesh": "ball"}]}
    (tmp_path / "scene.json").write_text(json.dumps(scene_doc))
    _assert_same_geometry(load_any(tmp_path / "scene.json").meshes[0], source)


def test_glb_with_a_texture_loads_it(tmp_path):
    source = _textured(_source())
    (tmp_path / "ball.glb").write_bytes(trimesh.Scene(source).export(file_type="glb"))
    scene = load_any(tmp_path / "ball.glb")
    mesh = scene.meshes[0]
    _assert_same_geometry(mesh, source)
    texture = scene.materials[mesh.material].texture
    factor = np.asarray(scene.materials[mesh.material].albedo, np.float32)
    np.testing.assert_allclose(texture, srgb_to_linear(TEXELS / 255.0) * factor, atol=1e-6)
    assert mesh.uvs is not None and mesh.uvs.shape == (len(mesh.vertices), 2)
