"""Shared helpers for the scene tests: small hand-built scenes and exact scene comparison."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

from nprt.scene.model import (
    Camera,
    DirectionalLight,
    Environment,
    Instance,
    Material,
    Mesh,
    PointLight,
    QuadLight,
    Scene,
)


def tetra(name: str = "tetra", material: int = 0, normals: bool = False,
          uvs: bool = False) -> Mesh:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float32)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.uint32)
    n = (v - 0.25) / np.linalg.norm(v - 0.25, axis=1, keepdims=True) if normals else None
    uv = np.array([[0, 0], [1, 0], [0, 1], [0.5, 0.5]], dtype=np.float32) if uvs else None
    return Mesh(name, v, f, None if n is None else n.astype(np.float32), uv, material)


def translate(x: float, y: float = 0.0, z: float = 0.0) -> np.ndarray:
    t = np.eye(4)
    t[:3, 3] = (x, y, z)
    return t


def rich_scene() -> Scene:
    """Every feature the JSON format carries, with awkward float64 values."""
    rng = np.random.default_rng(7)
    ring = np.arange(48)
    faces = np.stack([ring, ring + 1, ring + 2], axis=1).astype(np.uint32)  # never degenerate
    blob = Mesh("blob", rng.normal(size=(50, 3)).astype(np.float32), faces, material=1)
    rot = np.array([[0.6, -0.8, 0.0], [0.8, 0.6, 0.0], [0.0, 0.0, 1.0]])
    far = np.eye(4)
    far[:3, :3] = rot * 1e-4
    far[:3, 3] = (1e6 + 0.1, -3.3333333333333335, 2.0 / 3.0)
    return Scene(
        meshes=(tetra("tetra", 0, normals=True, uvs=True), blob),
        instances=(Instance(0, np.eye(4)), Instance(1, far), Instance(0, translate(0.1, 0.2, 0.3))),
        materials=(
            Material("textured", (0.5, 0.25, 0.125),
                     texture=rng.random((3, 5, 3)).astype(np.float32)),
            Material("lamp", (0.1, 0.2, 0.3), emission=(4.0, 5.0, 6.5)),
        ),
        quad_lights=(QuadLight((0, 5, 0), (1, 0, 0), (0, 0, 1), (10, 9, 8)),),
        point_lights=(PointLight((1, 2, 3), (0.5, 0.5, 0.25)),),
        directional_lights=(DirectionalLight((0, -1, 0.1), (2, 2, 2)),),
        environment=Environment("sky", zenith=(0.1, 0.2, 0.9), horizon=(0.9, 0.9, 0.8)),
        camera=Camera((1, 2, 3), (0, 0.5, 0), (0, 1, 0), 33.3),
        name="rich",
    )


def _same(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b)


def assert_scenes_equal(a: Scene, b: Scene) -> None:
    """Exact equality of everything a scene file stores (bit-for-bit arrays)."""
    assert a.name == b.name
    assert len(a.meshes) == len(b.meshes)
    for ma, mb in zip(a.meshes, b.meshes, strict=True):
        assert ma.name == mb.name and ma.material == mb.material
        for field in ("vertices", "faces", "normals", "uvs"):
            assert _same(getattr(ma, field), getattr(mb, field)), f"{ma.name}.{field} differs"
    assert len(a.instances) == len(b.instances)
    for ia, ib in zip(a.instances, b.instances, strict=True):
        assert ia.mesh == ib.mesh
        assert ib.transform.dtype == np.float64 and np.array_equal(ia.transform, ib.transform)
    assert len(a.materials) == len(b.materials)
    for xa, xb in zip(a.materials, b.materials, strict=True):
        assert (xa.name, tuple(xa.albedo), tuple(xa.emission)) == (
            xb.name, tuple(xb.albedo), tuple(xb.emission))
        assert _same(xa.texture, xb.texture)
    assert a.quad_lights == b.quad_lights
    assert a.point_lights == b.point_lights
    assert a.directional_lights == b.directional_lights
    assert a.environment == b.environment
    assert a.camera == b.camera


# ---------------------------------------------------------------- file-open audit

_RECORDERS: list[list[str]] = []


def _audit(event: str, args: tuple) -> None:
    # The "open" audit event fires for every Python-level open (io, os.open, numpy, PIL,
    # trimesh), in every thread: proof of what a loader read, not what it claims.
    if event == "open" and _RECORDERS and isinstance(args[0], str | bytes | os.PathLike):
        path = os.path.realpath(os.fsdecode(args[0]))
        for rec in _RECORDERS:
            rec.append(path)


sys.addaudithook(_audit)  # hooks cannot be removed; it is idle unless recording


@contextmanager
def recording_opens() -> Iterator[list[str]]:
    """Collect the real paths of every file opened inside the block."""
    opened: list[str] = []
    _RECORDERS.append(opened)
    try:
        yield opened
    finally:
        _RECORDERS[:] = [r for r in _RECORDERS if r is not opened]
