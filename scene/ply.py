"""Binary PLY files of triangles read with plyfile alone: what `meshfile.write_ply` writes,
so every mesh of a stored scene (`nprt.scene.store`). A shard of a stored scene reads its
meshes at start-up; through trimesh that meant importing trimesh, scipy and networkx first,
about 0.5 s of CPU in each shard process (K = 4 forest:small on two cores: each shard's
mesh load 0.5-1.3 s, its pool start 3.95-4.07 s against 2.9-3.4 s for the same scene held
in memory). Any other PLY (ASCII, polygons, other elements or properties, a texture file,
UVs beside vertices that no face uses) gives None and is read by trimesh as before, so what
a file means does not depend on the path it takes (tests/scene/test_ply.py holds the two to
the same arrays)."""

from __future__ import annotations

import functools
import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

# Vertex texture coordinates as trimesh's PLY loader names them, in its order of preference.
UV_NAMES = (("texture_u", "texture_v"), ("u", "v"), ("s", "t"))
POSITION, NORMAL = ("x", "y", "z"), ("nx", "ny", "nz")


@functools.cache
def _plyfile():
    """The plyfile module; None, said once, in an install without it (a bundle of wheels
    installed without their dependencies): trimesh then reads every PLY."""
    try:
        import plyfile
    except ImportError:
        log.warning("plyfile is not installed: PLY files are read through trimesh")
        return None
    return plyfile


def read_triangle_ply(path: Path) -> dict | None:
    """`meshfile.mesh_arrays` of a binary PLY holding only vertices (position, and maybe
    normals and one pair of texture coordinates) and triangles; None for any other file.

    returns : vertices (v, 3) float64, faces (f, 3) int64, normals (v, 3) float32 or None,
              uvs (v, 2) float64 or None
    """
    plyfile = _plyfile()
    if plyfile is None:
        return None
    try:
        ply = plyfile.PlyData.read(str(path), known_list_len={"face": {"vertex_indices": 3}})
    except (plyfile.PlyParseError, ValueError, EOFError, OSError):
        return None  # trimesh reads it (polygons, say), or says what is wrong with it
    names = [e.name for e in ply.elements]
    if ply.text or names != ["vertex", "face"] or any("texture" in c.lower()
                                                      for c in ply.comments):
        return None
    vertex, face = ply["vertex"].data, ply["face"].data
    props = set(vertex.dtype.names)
    uv = next((pair for pair in UV_NAMES if set(pair) <= props), ())
    if (face.dtype.names != ("vertex_indices",) or not set(POSITION) <= props
            or not props <= {*POSITION, *NORMAL, *uv}
            or props & set(NORMAL) not in (set(), set(NORMAL))):
        return None
    faces = np.array(face["vertex_indices"], np.int64).reshape(-1, 3)
    if not len(faces) or faces.min() < 0 or faces.max() >= len(vertex):
        return None  # trimesh's reading, then `build_mesh`, say what is wrong
    if uv and len(np.unique(faces)) != len(vertex):
        return None  # with UVs, trimesh drops the vertices that no face uses
    from nprt.scene.model import VERTEX_DTYPE

    def columns(keys, dtype):
        return np.column_stack([np.asarray(vertex[k], dtype) for k in keys])

    return {"vertices": columns(POSITION, np.float64).reshape(-1, 3),
            "faces": faces,
            "normals": columns(NORMAL, VERTEX_DTYPE) if "nx" in props else None,
            "uvs": columns(uv, np.float64) if uv else None}
