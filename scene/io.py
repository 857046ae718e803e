"""The front door for scenes: `load_any` reads a demo name, a JSON scene, a glTF/GLB file
or a lone mesh file. The formats live in their own modules (`json_load`, `json_save`,
`meshfile`, `texture`, `gltf`); their public names are re-exported here."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nprt.scene.errors import SceneError
from nprt.scene.json_load import load_scene, read_spec
from nprt.scene.json_save import save_scene
from nprt.scene.meshfile import MESH_SUFFIXES, build_mesh, mesh_arrays, open_mesh_file
from nprt.scene.model import (
    Camera,
    Environment,
    Instance,
    Material,
    Mesh,
    Scene,
    instance_world_bounds,
)
from nprt.scene.paths import FileRefs
from nprt.scene.texture import srgb_to_linear

__all__ = ["MESH_SUFFIXES", "load_any", "load_scene", "read_spec", "save_scene",
           "scene_from_meshes", "srgb_to_linear"]


def frame_camera(bounds: np.ndarray, fov_deg: float = 40.0) -> Camera:
    """A camera looking at the box from the front-right, above. bounds : (2, 3) float64."""
    lo, hi = np.asarray(bounds, dtype=np.float64)
    centre = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-6)
    dist = radius / np.sin(np.radians(fov_deg) / 2.0)
    direction = np.array([0.6, 0.45, 1.0]) / np.linalg.norm([0.6, 0.45, 1.0])
    return Camera(tuple((centre + dist * direction).tolist()), tuple(centre.tolist()),
                  (0.0, 1.0, 0.0), fov_deg)


def scene_from_meshes(meshes: list[Mesh], transforms: list[tuple[int, np.ndarray]],
                      materials: tuple[Material, ...], name: str) -> Scene:
    """A scene with a framing camera and a daylight sky, for files without their own."""
    instances = tuple(Instance(mi, xf) for mi, xf in transforms)
    bare = Scene(tuple(meshes), instances, materials, name=name)
    wb = instance_world_bounds(bare)
    bounds = np.stack([wb[:, 0].min(axis=0), wb[:, 1].max(axis=0)])
    sky = Environment(kind="sky", zenith=(0.35, 0.5, 0.9), horizon=(0.9, 0.9, 0.85))
    return Scene(tuple(meshes), instances, materials, environment=sky,
                 camera=frame_camera(bounds), name=name)


def load_any(source, size: str = "default", seed: int = 0, root: Path | None = None) -> Scene:
    """A demo name ("forest", "city:small"), a .json scene, a .glb/.gltf file or a mesh file.
    With `root` set (an upload), no file outside `root` is read."""
    from nprt.scene import demos, gltf  # deferred: gltf imports trimesh and this module

    if isinstance(source, str) and not source.lower().endswith((".json", *MESH_SUFFIXES)):
        name, _, demo_size = source.partition(":")
        if name in demos.DEMOS:
            return demos.make_demo(name, size=demo_size or size, seed=seed)
    path = Path(source)
    suffix = path.suffix.lower()
    if suffix == ".json":
        return load_scene(path, root)
    if suffix in (".glb", ".gltf"):
        return gltf.load_gltf(path, root)
    if suffix in MESH_SUFFIXES:
        refs = FileRefs(path.parent, root)
        path = refs.resolve(path.name, "mesh file", "")
        where = refs.show(path)
        tm, named = open_mesh_file(path, where, refs)
        mesh = build_mesh(path.stem, where=where, **mesh_arrays(tm))
        material = Material()
        if any(p.suffix.lower() == ".mtl" for p in named):  # an OBJ whose MTL was read
            material = gltf.file_material(tm.visual, path.stem, len(tm.vertices))
        return scene_from_meshes([mesh], [(0, np.eye(4))], (material,), path.stem)
    if not path.exists():
        raise SceneError(
            f"unknown scene {str(source)!r}: not a demo ({', '.join(demos.DEMOS)}) "
            f"and no such file"
        )
    raise SceneError(f"{path}: unsupported scene format {suffix!r} (want .json, .glb, .gltf)")
