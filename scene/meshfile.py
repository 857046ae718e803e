"""Mesh files: OBJ/PLY/STL/OFF/GLB read through trimesh, a validated `Mesh` built from
arrays (degenerate triangles dropped and counted), and binary PLY written."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from nprt.scene.errors import SceneError
from nprt.scene.model import INDEX_DTYPE, VERTEX_DTYPE, Mesh, validate_mesh
from nprt.scene.paths import FileRefs, load_trimesh
from nprt.scene.ply import read_triangle_ply

if TYPE_CHECKING:
    import trimesh

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")


def drop_degenerate(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, int]:
    """Remove zero-area triangles (repeated or collinear corners, exactly, in float64).

    vertices : (v, 3) float32
    faces    : (f, 3) uint32
    returns  : (kept faces (g, 3) uint32, number dropped)
    """
    tri = vertices.astype(np.float64)[faces]  # (f, 3, 3)
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (f, 3)
    keep = np.any(cross != 0.0, axis=1)
    return faces[keep], int(len(faces) - keep.sum())


def build_mesh(
    name: str,
    vertices,
    faces,
    normals=None,
    uvs=None,
    material: int = 0,
    where: str | None = None,
) -> Mesh:
    """Validate, cast to the model's dtypes and drop degenerate triangles.

    vertices : (v, 3) float, faces : (f, 3) int, normals : (v, 3) or None, uvs : (v, 2) or None
    """
    where = where or f"mesh {name!r}"
    try:
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces)
        if f.dtype.kind in "fO" and not isinstance(faces, np.ndarray):
            f = np.asarray(faces, dtype=object)  # Python ints past int64 stay exact
    except (ValueError, TypeError) as e:
        raise SceneError(f"{where}: vertices/faces are not numeric arrays: {e}") from None
    v = v.reshape(0, 3) if v.size == 0 else v
    f = _face_indices(f, len(v), where)
    if np.isfinite(v).all() and np.abs(v).max(initial=0.0) > np.finfo(VERTEX_DTYPE).max:
        raise SceneError(f"{where}: vertex coordinates overflow float32")
    n = None if normals is None else np.ascontiguousarray(normals, dtype=VERTEX_DTYPE)
    uv = None if uvs is None else np.ascontiguousarray(uvs, dtype=VERTEX_DTYPE)
    raw = Mesh(name, np.ascontiguousarray(v, dtype=VERTEX_DTYPE), f, n, uv, material)
    validate_mesh(raw, where)
    for label, arr in (("normals", n), ("uvs", uv)):
        if arr is not None and not np.isfinite(arr).all():
            raise SceneError(f"{where}: {label} contain non-finite values")
    kept, dropped = drop_degenerate(raw.vertices, f)
    if len(kept) == 0:
        raise SceneError(f"{where}: all {len(f)} triangles are degenerate (zero area)")
    if dropped:
        log.info("%s: dropped %d degenerate triangles of %d", where, dropped, len(f))
    return Mesh(name, raw.vertices, kept, n, uv, material, dropped)


def _face_indices(f: np.ndarray, n_vertices: int, where: str) -> np.ndarray:
    """f : (f, 3) integers of any dtype (object: Python ints) -> (f, 3) uint32, refusing
    non-integers, negatives and indices past the vertices before a cast could wrap them."""
    if f.size == 0:
        return f.reshape(0, 3).astype(INDEX_DTYPE)
    if f.dtype == object:
        flat = f.ravel().tolist()
        if not all(isinstance(x, int | np.integer) for x in flat):
            raise SceneError(f"{where}: face indices must be integers")
        lo, hi = min(flat), max(flat)
    elif np.issubdtype(f.dtype, np.integer):
        lo, hi = f.min(), f.max()
    else:
        raise SceneError(f"{where}: face indices must be integers, got {f.dtype}")
    if lo < 0:
        raise SceneError(f"{where}: face index {int(lo)} is negative")
    if hi >= n_vertices:
        raise SceneError(f"{where}: face index {int(hi)} out of range for {n_vertices} vertices")
    return np.ascontiguousarray(f.astype(np.int64), dtype=INDEX_DTYPE)


def open_mesh_file(path: Path, where: str,
                   refs: FileRefs | None = None) -> tuple[trimesh.Trimesh, list[Path]]:
    """Read one mesh file through trimesh (multi-mesh files are flattened into one); `path`
    comes from `refs.resolve`, and the files it names (MTL, textures, glTF buffers) are
    read through `refs` too. Returns the mesh and those other files."""
    import trimesh  # here, not at import: a driver planning from metadata never needs it

    refs = refs or FileRefs(path.parent)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise SceneError(f"{where}: unsupported mesh format {path.suffix!r} ({refs.show(path)})")
    loaded, named = load_trimesh(path, refs, f"mesh file {refs.show(path)}", where,
                                 force="scene", process=False)
    meshes = [g for g in loaded.geometry.values() if isinstance(g, trimesh.Trimesh)]
    nodes = loaded.graph.nodes_geometry
    if not meshes:
        raise SceneError(f"{where}: {refs.show(path)} holds no triangle mesh")
    if len(meshes) == 1 and len(nodes) == 1 and np.array_equal(loaded.graph[nodes[0]][0],
                                                                np.eye(4)):
        return meshes[0], named  # as loaded: concatenating would drop the file's normals
    return loaded.to_mesh(), named


def mesh_arrays(tm: trimesh.Trimesh) -> dict:
    """What `build_mesh` takes from a loaded mesh file.

    returns : dict with vertices (v, 3), faces (f, 3), normals (v, 3) or None, uvs (v, 2) or None
    """
    uv = getattr(tm.visual, "uv", None)
    uv = uv if uv is not None and np.shape(uv) == (len(tm.vertices), 2) else None
    normals = _ply_normals(tm) if "_ply_raw" in tm.metadata else file_normals(tm)
    return {"vertices": tm.vertices, "faces": tm.faces, "normals": normals, "uvs": uv}


def read_mesh_file(path: Path, where: str, refs: FileRefs | None = None) -> dict:
    """`mesh_arrays` of `open_mesh_file`; a binary PLY of triangles (every mesh of a stored
    scene) is read without trimesh (`nprt.scene.ply`)."""
    if path.suffix.lower() == ".ply":
        arrays = read_triangle_ply(path)
        if arrays is not None:
            return arrays
    return mesh_arrays(open_mesh_file(path, where, refs)[0])


def file_normals(tm: trimesh.Trimesh) -> np.ndarray | None:
    """Vertex normals the file carried (OBJ `vn`, glTF NORMAL), or None: trimesh keeps
    those in its cache; computed ones are not there until asked for."""
    if "vertex_normals" in tm._cache:
        return np.asarray(tm.vertex_normals)
    return None


def _ply_normals(tm: trimesh.Trimesh) -> np.ndarray | None:
    """The file's own nx/ny/nz as (v, 3) float32, or None. trimesh recomputes normals on
    load; the file's survive in the raw PLY data: a structured array for binary PLY, a
    dict of (v, 1) columns for ASCII PLY."""
    raw = tm.metadata.get("_ply_raw", {}).get("vertex", {}).get("data")
    names = raw.keys() if isinstance(raw, dict) else getattr(getattr(raw, "dtype", None),
                                                             "names", None)
    if not names or not {"nx", "ny", "nz"} <= set(names):
        return None
    normals = np.column_stack([np.ravel(raw[k]) for k in ("nx", "ny", "nz")])  # (v, 3)
    if len(normals) != len(tm.vertices):
        return None
    return normals.astype(VERTEX_DTYPE)


def write_ply(mesh: Mesh, path: Path) -> None:
    """mesh as binary PLY at path: vertices, faces, and normals and uvs when it has them."""
    import trimesh
    from trimesh.exchange.ply import export_ply

    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False, validate=False)
    if mesh.normals is not None:
        for i, axis in enumerate("xyz"):
            tm.vertex_attributes["n" + axis] = mesh.normals[:, i].astype(VERTEX_DTYPE)
    if mesh.uvs is not None:
        tm.visual = trimesh.visual.TextureVisuals(uv=mesh.uvs)
    path.write_bytes(export_ply(tm, encoding="binary", vertex_normal=False))
