"""The scene store's PLY files read without trimesh (nprt.scene.ply) give the arrays trimesh
gives; every other PLY still goes through trimesh."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from nprt.scene.demos import make_demo
from nprt.scene.errors import SceneError
from nprt.scene.io import save_scene
from nprt.scene.meshfile import mesh_arrays, open_mesh_file, read_mesh_file, write_ply
from nprt.scene.model import Mesh
from nprt.scene.ply import read_triangle_ply

REPO = Path(__file__).resolve().parents[2]


def _by_trimesh(path: Path) -> dict:
    return mesh_arrays(open_mesh_file(path, "test")[0])


def _assert_same(fast: dict, slow: dict) -> None:
    for key in ("vertices", "faces", "normals", "uvs"):
        a, b = fast[key], slow[key]
        assert (a is None) == (b is None), key
        if a is not None:
            assert np.array_equal(np.asarray(a, np.float64), np.asarray(b, np.float64)), key


@pytest.mark.parametrize("name", ["forest", "city", "sculpture", "windy"])
def test_every_mesh_the_store_writes_reads_as_trimesh_reads_it(tmp_path, name):
    save_scene(make_demo(name, "tiny"), tmp_path / "scene.json")
    files = sorted(tmp_path.glob("*.ply"))
    assert files
    for path in files:
        fast = read_triangle_ply(path)
        assert fast is not None, path
        _assert_same(fast, _by_trimesh(path))


def _quad() -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    return v, np.array([[0, 1, 2], [0, 2, 3]], np.uint32)


def test_normals_and_texture_coordinates_come_through(tmp_path):
    v, f = _quad()
    normals = np.tile(np.float32([0, 0, 1]), (4, 1))
    uvs = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    path = tmp_path / "m.ply"
    write_ply(Mesh("m", v, f, normals, uvs, 0), path)
    fast = read_triangle_ply(path)
    assert fast is not None and fast["normals"] is not None and fast["uvs"] is not None
    _assert_same(fast, _by_trimesh(path))


@pytest.mark.parametrize("body", [
    # ASCII
    "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
    "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
    "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
    # a quad: trimesh splits it in two triangles
    "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
    "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
    "0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n",
])
def test_any_other_ply_goes_through_trimesh(tmp_path, body):
    path = tmp_path / "m.ply"
    path.write_text(body)
    assert read_triangle_ply(path) is None
    _assert_same(read_mesh_file(path, "test"), _by_trimesh(path))


def test_a_binary_polygon_or_a_vertex_colour_is_left_to_trimesh(tmp_path):
    v, f = _quad()
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\n"
              "property float y\nproperty float z\n{extra}element face 1\n"
              "property list uchar int vertex_indices\nend_header\n")
    quad = header.format(extra="").encode() + v.tobytes() + bytes([4]) + np.int32(
        [0, 1, 2, 3]).tobytes()
    (tmp_path / "quad.ply").write_bytes(quad)
    red = np.zeros(4, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1")])
    red["x"], red["y"], red["z"], red["red"] = v[:, 0], v[:, 1], v[:, 2], 255
    coloured = (header.format(extra="property uchar red\n").encode() + red.tobytes()
                + bytes([3]) + np.int32(f[0]).tobytes())
    (tmp_path / "red.ply").write_bytes(coloured)
    for name in ("quad.ply", "red.ply"):
        path = tmp_path / name
        assert read_triangle_ply(path) is None, name
        _assert_same(read_mesh_file(path, "test"), _by_trimesh(path))


def test_a_truncated_ply_fails_as_it_did_through_trimesh(tmp_path):
    path = tmp_path / "m.ply"
    v, f = _quad()
    write_ply(Mesh("m", v, f, None, None, 0), path)
    path.write_bytes(path.read_bytes()[:-7])
    assert read_triangle_ply(path) is None
    with pytest.raises(SceneError):
        read_mesh_file(path, "test")


_LOAD = """
import json, sys
from nprt.scene.store import open_scene
meta = open_scene(sys.argv[1])
meshes = meta.source.load_meshes(tuple(range(len(meta.meshes))))
print(json.dumps({"meshes": len(meshes), "trimesh": "trimesh" in sys.modules}))
"""


def test_a_shard_loads_a_stored_scene_without_importing_trimesh(tmp_path):
    env = {**os.environ, "NPRT_SCENE_CACHE": str(tmp_path)}
    subprocess.run([sys.executable, "-c", _LOAD, "forest:tiny"], env=env, cwd=REPO,
                   check=True, capture_output=True)  # writes the scene (trimesh, once)
    res = subprocess.run([sys.executable, "-c", _LOAD, "forest:tiny"], env=env, cwd=REPO,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out == {"meshes": 5, "trimesh": False}


def test_random_meshes_read_as_trimesh_reads_them(tmp_path):
    """Normals or not, UVs or not, vertices that no face uses or not (with UVs trimesh
    drops those, so such a file is left to it)."""
    rng = np.random.default_rng(7)
    path = tmp_path / "m.ply"
    fast_reads = 0
    for trial in range(120):
        n = int(rng.integers(3, 30))
        faces = rng.integers(0, n, (int(rng.integers(1, 50)), 3)).astype(np.uint32)
        normals = rng.random((n, 3)).astype(np.float32) if trial % 2 else None
        uvs = rng.random((n, 2)).astype(np.float32) if trial % 3 else None
        write_ply(Mesh("m", rng.random((n, 3)).astype(np.float32), faces, normals, uvs, 0),
                  path)
        fast = read_triangle_ply(path)
        if fast is None:
            assert uvs is not None and len(np.unique(faces)) < n, trial
            continue
        fast_reads += 1
        _assert_same(fast, _by_trimesh(path))
    assert fast_reads > 60


def test_a_ply_without_faces_is_left_to_trimesh(tmp_path):
    path = tmp_path / "points.ply"
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
              "property float y\nproperty float z\nelement face 0\n"
              "property list uchar int vertex_indices\nend_header\n")
    path.write_bytes(header.encode() + np.zeros((3, 3), np.float32).tobytes())
    assert read_triangle_ply(path) is None
