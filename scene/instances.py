"""Instance tables as arrays on disk: the `.npz` file that a JSON scene may name instead of
listing one object per instance (`"instances": {"file": "scene.instances.npz"}`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nprt.scene.errors import SceneError
from nprt.scene.model import Instances, validate_transforms

# The arrays of an instance file, and nothing else.
MESH_KEY = "mesh"  # (m,) integer index into the scene's meshes
TRANSFORM_KEY = "transform"  # (m, 4, 4) float affine local -> world, row-major


def read_instance_file(path: Path, mesh_names: list[str], where: str) -> Instances:
    """Instances from an `.npz` holding `mesh` (m,) integer and `transform` (m, 4, 4)
    float arrays; every problem is a SceneError naming `where`, the file and the array."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{where}: instance file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except Exception as e:  # zipfile/numpy raise many types for bad files
        raise SceneError(f"{where}: could not read instance file {path}: {e}") from None
    where = f"{where} ({path.name})"
    keys = {MESH_KEY, TRANSFORM_KEY}
    if arrays.keys() != keys:
        raise SceneError(f"{where}: needs exactly the arrays {sorted(keys)}, "
                         f"got {sorted(arrays)}")
    mesh, xf = arrays[MESH_KEY], arrays[TRANSFORM_KEY]
    if mesh.ndim != 1 or not np.issubdtype(mesh.dtype, np.integer):
        raise SceneError(f"{where}: '{MESH_KEY}' must be a (m,) integer array, "
                         f"got shape {mesh.shape} dtype {mesh.dtype}")
    if len(mesh) == 0:
        raise SceneError(f"{where}: '{MESH_KEY}' is empty (a scene needs instances)")
    if xf.shape != (len(mesh), 4, 4) or xf.dtype.kind not in "fiu":
        raise SceneError(f"{where}: '{TRANSFORM_KEY}' must be a ({len(mesh)}, 4, 4) float "
                         f"array (one per '{MESH_KEY}' entry), got shape {xf.shape} "
                         f"dtype {xf.dtype}")
    bad = np.flatnonzero((mesh < 0) | (mesh >= len(mesh_names)))
    if len(bad):
        i = int(bad[0])
        raise SceneError(f"{where}: '{MESH_KEY}'[{i}] = {int(mesh[i])} is not a mesh index "
                         f"(there are {len(mesh_names)} meshes); {len(bad)} bad in all")
    validate_transforms(xf, lambda i: f"{where}: '{TRANSFORM_KEY}'[{i}] "
                                      f"(mesh {mesh_names[mesh[i]]!r})")
    return Instances(mesh, xf)


def write_instance_file(path: Path, instances: Instances) -> Path:
    """Write `instances` as the `.npz` that `read_instance_file` reads (uncompressed:
    random transforms hardly compress, and loading stays a copy)."""
    path = Path(path)
    with path.open("wb") as f:
        np.savez(f, **{MESH_KEY: np.asarray(instances.mesh, np.int32),
                       TRANSFORM_KEY: np.asarray(instances.transform, np.float64)})
    return path
