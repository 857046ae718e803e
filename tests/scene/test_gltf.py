"""glTF/GLB loading: reused meshes become instances, node transforms, base colour, texture."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from PIL import Image
from trimesh.visual.material import PBRMaterial

from nprt.scene.errors import SceneError
from nprt.scene.gltf import load_gltf
from nprt.scene.texture import srgb_to_linear
from tests.scene._util import translate


def _shared_geometry_glb(path, n_nodes: int = 3):
    """One box geometry referenced by n nodes (the glTF's single mesh, used n times)."""
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.creation.box(), geom_name="box", node_name="node0",
                       transform=translate(0.0))
    for i in range(1, n_nodes):
        scene.graph.update(frame_to=f"node{i}", frame_from=scene.graph.base_frame,
                           geometry="box", matrix=translate(3.0 * i, 0.5 * i))
    path.write_bytes(scene.export(file_type="glb"))
    return path


def test_gltf_mesh_reused_by_three_nodes_becomes_one_base_mesh_with_three_instances(tmp_path):
    scene = load_gltf(_shared_geometry_glb(tmp_path / "reuse.glb"))
    assert len(scene.meshes) == 1
    assert len(scene.instances) == 3
    assert {i.mesh for i in scene.instances} == {0}
    offsets = sorted(tuple(i.transform[:3, 3]) for i in scene.instances)
    assert offsets == [(0.0, 0.0, 0.0), (3.0, 0.5, 0.0), (6.0, 1.0, 0.0)]
    assert all(i.transform.dtype == np.float64 for i in scene.instances)
    assert len(scene.meshes[0].faces) == 12


def test_gltf_identical_copies_under_different_names_are_merged(tmp_path):
    scene = trimesh.Scene()
    for i in range(3):  # add_geometry makes three named copies: box, box_1, box_2
        scene.add_geometry(trimesh.creation.box(), geom_name="box", node_name=f"n{i}",
                           transform=translate(2.0 * i))
    scene.add_geometry(trimesh.creation.icosphere(1), geom_name="ball", node_name="b")
    (tmp_path / "copies.glb").write_bytes(scene.export(file_type="glb"))
    loaded = load_gltf(tmp_path / "copies.glb")
    assert len(loaded.meshes) == 2
    per_mesh = np.bincount([i.mesh for i in loaded.instances])
    assert sorted(per_mesh.tolist()) == [1, 3]


def test_gltf_node_world_transform_includes_parents(tmp_path):
    scene = trimesh.Scene()
    scene.graph.update(frame_to="parent", frame_from=scene.graph.base_frame,
                       matrix=translate(10.0))
    rot = trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0])
    scene.add_geometry(trimesh.creation.box(), geom_name="box", node_name="child",
                       parent_node_name="parent", transform=rot @ translate(1.0))
    (tmp_path / "tree.glb").write_bytes(scene.export(file_type="glb"))
    inst = load_gltf(tmp_path / "tree.glb").instances
    assert len(inst) == 1
    np.testing.assert_allclose(inst[0].transform, translate(10.0) @ rot @ translate(1.0),
                               atol=1e-6)


def test_gltf_base_colour_factor_becomes_albedo(tmp_path):
    box = trimesh.creation.box()
    box.visual = trimesh.visual.TextureVisuals(
        material=PBRMaterial(baseColorFactor=[0.2, 0.4, 0.6, 1.0], emissiveFactor=[0, 0, 0]))
    trimesh.Scene(box).export(tmp_path / "red.glb")
    scene = load_gltf(tmp_path / "red.glb")
    mat = scene.materials[scene.meshes[0].material]
    np.testing.assert_allclose(mat.albedo, [0.2, 0.4, 0.6], atol=1.0 / 255)
    assert mat.texture is None and scene.meshes[0].uvs is None


def test_gltf_base_colour_texture_becomes_linear_texture_with_uvs(tmp_path):
    rng = np.random.default_rng(0)
    texels = (rng.random((4, 6, 3)) * 255).astype(np.uint8)
    box = trimesh.creation.box()
    uv = rng.random((len(box.vertices), 2))
    box.visual = trimesh.visual.TextureVisuals(
        uv=uv, material=PBRMaterial(baseColorFactor=[1.0, 0.5, 1.0, 1.0],
                                    baseColorTexture=Image.fromarray(texels)))
    trimesh.Scene(box).export(tmp_path / "tex.glb")
    scene = load_gltf(tmp_path / "tex.glb")
    mesh = scene.meshes[0]
    tex = scene.materials[mesh.material].texture
    assert tex.dtype == np.float32 and tex.shape == (4, 6, 3)
    factor = np.array([1.0, 128 / 255, 1.0], dtype=np.float32)  # the factor is baked in
    np.testing.assert_allclose(tex, srgb_to_linear(texels / 255.0) * factor, atol=1e-6)
    assert mesh.uvs.dtype == np.float32 and mesh.uvs.shape == (len(mesh.vertices), 2)
    np.testing.assert_allclose(mesh.uvs, uv, atol=1e-6)


def test_gltf_gets_a_camera_that_looks_at_it(tmp_path):
    scene = load_gltf(_shared_geometry_glb(tmp_path / "reuse.glb"))
    eye, target = np.array(scene.camera.eye), np.array(scene.camera.target)
    assert 0.0 <= target[0] <= 6.0 and np.linalg.norm(eye - target) > 3.0
    assert scene.environment.kind == "sky"


def test_missing_gltf_file_is_reported(tmp_path):
    with pytest.raises(SceneError, match="glTF file not found"):
        load_gltf(tmp_path / "nope.glb")


def test_gltf_node_with_singular_transform_is_named(tmp_path):
    scene = trimesh.Scene()
    flat = np.diag([1.0, 0.0, 1.0, 1.0])
    scene.add_geometry(trimesh.creation.box(), geom_name="box", node_name="flat",
                       transform=flat)
    (tmp_path / "flat.glb").write_bytes(scene.export(file_type="glb"))
    with pytest.raises(SceneError, match=r"node 'flat'.*singular"):
        load_gltf(tmp_path / "flat.glb")
