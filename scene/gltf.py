"""glTF 2.0 / GLB loading through trimesh: each glTF mesh used by several nodes becomes one
base mesh with one instance per node, with base-colour factor and texture as the material.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
from pathlib import Path

import numpy as np
import trimesh

from nprt.scene.errors import SceneError
from nprt.scene.gltf_anim import gltf_animation
from nprt.scene.io import scene_from_meshes
from nprt.scene.meshfile import build_mesh, file_normals
from nprt.scene.model import TRANSFORM_DTYPE, Material, Mesh, Scene, validate_transform
from nprt.scene.paths import FileRefs, load_trimesh
from nprt.scene.texture import srgb_to_linear

log = logging.getLogger(__name__)


def load_gltf(path, root: Path | None = None) -> Scene:
    """Load a .glb/.gltf file; meshes keep their local space, node world transforms become
    instances, and identical meshes (geometry, UVs, normals, material) are stored once.
    The scene gets a framing camera and a sky (glTF lights and camera poses are ignored;
    the file camera's znear becomes the framing camera's near distance). External buffers
    and images resolve next to the file, inside `root` when it is set (an upload)."""
    refs = FileRefs(Path(path).parent, root)
    path = refs.resolve(Path(path).name, "glTF file", "")
    shown = refs.show(path)
    tm, _ = load_trimesh(path, refs, "glTF", shown, force="scene", process=False)
    meshes: list[Mesh] = []
    materials: list[Material] = []
    mesh_of: dict[str, int] = {}  # geometry name -> base mesh index
    mesh_of_content: dict[tuple, int] = {}  # _content_key -> base mesh index
    material_of: dict = {}  # id(trimesh material) or content key -> material index
    placements: list[tuple[int, np.ndarray]] = []
    node_names: list[tuple] = []  # (trimesh frame, its parent frame) of each placement
    for node in sorted(tm.graph.nodes_geometry, key=str):
        xf, geom_name = tm.graph[node]
        geom = tm.geometry[geom_name]
        if not isinstance(geom, trimesh.Trimesh):
            log.warning("%s: node %r holds a %s, not triangles; skipped",
                        shown, node, type(geom).__name__)
            continue
        if geom_name not in mesh_of:
            mat = _material_index(geom, geom_name, materials, material_of)
            tex = materials[mat].texture is not None
            mesh = build_mesh(
                str(geom_name), geom.vertices, geom.faces,
                normals=file_normals(geom),
                uvs=np.asarray(geom.visual.uv) if tex else None,
                material=mat, where=f"{shown}: mesh {geom_name!r}",
            )
            # Exporters often write one copy per node; identical copies become one base mesh.
            key = _content_key(mesh)
            if key not in mesh_of_content:
                mesh_of_content[key] = len(meshes)
                meshes.append(mesh)
            mesh_of[geom_name] = mesh_of_content[key]
        xf = np.asarray(xf, dtype=TRANSFORM_DTYPE)
        validate_transform(xf, f"{shown}: node {node!r} (mesh {geom_name!r})")
        placements.append((mesh_of[geom_name], xf))
        # A node with several primitives places each under a child frame of its own.
        node_names.append((node, tm.graph.transforms.parents.get(node)))
    if not placements:
        raise SceneError(f"{shown}: no triangle meshes in the glTF scene")
    log.info("%s: %d base meshes, %d instances", shown, len(meshes), len(placements))
    scene = scene_from_meshes(meshes, placements, tuple(materials) or (Material(),), path.stem)
    znear = _file_znear(tm)
    if znear is not None:
        scene = dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, near=znear))
    anim = gltf_animation(path, refs, shown, node_names)
    if anim is None:
        return scene
    return dataclasses.replace(scene, animation=anim, check_meshes=False).at_frame(0)



def _file_znear(tm: trimesh.Scene) -> float | None:
    """znear of the file's perspective camera (trimesh reads the first) in world units:
    scaled by its node's uniform scale, if any. None when the file has no camera."""
    if not tm.has_camera:
        return None
    xf = np.asarray(tm.camera_transform, dtype=np.float64)
    scale = float(np.cbrt(abs(np.linalg.det(xf[:3, :3]))))
    znear = float(tm.camera.z_near) * (scale if np.isfinite(scale) and scale > 0 else 1.0)
    if not (np.isfinite(znear) and znear >= 0.0):
        raise SceneError(f"camera znear {tm.camera.z_near!r} is not a distance >= 0")
    return znear


def _content_key(mesh: Mesh) -> tuple:
    extra = hashlib.sha256()
    for arr in (mesh.normals, mesh.uvs):
        extra.update(b"-" if arr is None else arr.tobytes())
    return mesh.content_hash, extra.hexdigest(), mesh.material


def _material_index(geom: trimesh.Trimesh, geom_name: str, materials: list[Material],
                    material_of: dict) -> int:
    """Index of the geometry's material in `materials`, appending it if new. Materials that
    render the same (albedo, emission, texture) are stored once, whatever their names."""
    source = getattr(geom.visual, "material", None)
    if source is not None and id(source) in material_of:
        return material_of[id(source)]
    mat = _convert_material(geom.visual, source, geom_name, len(geom.vertices))
    tex = b"" if mat.texture is None else mat.texture.tobytes()
    shape = None if mat.texture is None else mat.texture.shape
    key = (mat.albedo, mat.emission, shape, hashlib.sha256(tex).hexdigest())
    if key not in material_of:
        material_of[key] = len(materials)
        materials.append(mat)
    if source is not None:
        material_of[id(source)] = material_of[key]
    return material_of[key]


def file_material(visual, name: str, n_vertices: int) -> Material:
    """The material a loaded mesh file carries (an OBJ's MTL: Kd, map_Kd)."""
    return _convert_material(visual, getattr(visual, "material", None), name, n_vertices)


def _convert_material(visual, source, geom_name: str, n_vertices: int) -> Material:
    """Base-colour factor -> albedo; base-colour texture (times the factor) -> texture."""
    name = str(getattr(source, "name", None) or geom_name)
    if source is None:  # ColorVisuals: one colour for the whole mesh
        rgba = np.asarray(visual.main_color, dtype=np.float64) / 255.0
        return Material(name, _albedo(rgba[:3]))
    if hasattr(source, "baseColorFactor"):
        factor = source.baseColorFactor
        image = source.baseColorTexture
        emission = source.emissiveFactor
    else:  # SimpleMaterial (OBJ/MTL through glTF-less paths)
        factor, image, emission = source.diffuse, source.image, None
    rgb = np.ones(3) if factor is None else np.asarray(factor, dtype=np.float64)[:3]
    rgb = rgb / 255.0 if np.asarray(factor).dtype == np.uint8 else rgb
    uv = getattr(visual, "uv", None)
    texture = None
    if image is not None and uv is not None and np.shape(uv) == (n_vertices, 2):
        texels = np.asarray(image.convert("RGB"), dtype=np.float32) / 255.0  # (h, w, 3)
        texture = (srgb_to_linear(texels) * rgb.astype(np.float32)).astype(np.float32)
    elif image is not None:
        log.warning("mesh %r: base-colour texture without UVs; using the factor only", geom_name)
    emit = (0.0, 0.0, 0.0) if emission is None else tuple(
        float(x) for x in np.clip(np.asarray(emission, dtype=np.float64)[:3], 0.0, None))
    return Material(name, _albedo(rgb), emit, texture)


def _albedo(rgb: np.ndarray) -> tuple[float, float, float]:
    return tuple(float(x) for x in np.clip(rgb, 0.0, 1.0))
