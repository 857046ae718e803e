"""4x4 transforms: a translate/rotate/scale matrix (`trs_matrix`, the scene file's form),
and moving a whole scene by a similarity x -> s R x + t (instances, camera, lights), with
the radiometry adjusted so that the rendered image must not change: the invariance that
the numerics tests and `bench/render/bench_extremes.py` check.

Radiance (quad lights, emission, environment) and irradiance (directional lights) are
invariant under a similarity; a point light's intensity scales by s^2, since its
irradiance falls off with the square of a distance that scales by s.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from nprt.scene.errors import SceneError
from nprt.scene.model import TRANSFORM_DTYPE, Camera, Instance, Scene

# A 'sky' environment blends by the direction's +y component: only rotations that keep
# +y (about the y axis) leave it unchanged.
_UP = np.array([0.0, 1.0, 0.0])


def similarity(scale: float = 1.0, translate=(0.0, 0.0, 0.0),
               rotate_y_deg: float = 0.0) -> np.ndarray:
    """(4, 4) float64: x -> scale * R_y(rotate_y_deg) x + translate."""
    a = np.radians(rotate_y_deg)
    c, s = np.cos(a), np.sin(a)
    m = np.eye(4)
    m[:3, :3] = scale * np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    m[:3, 3] = np.asarray(translate, np.float64)
    return m


def split_similarity(m: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale s, rotation (3, 3), translation (3,)) of a (4, 4) similarity; ValueError
    names the matrix when it is not one (non-uniform scale, shear, reflection)."""
    m = np.asarray(m, np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all() or not np.allclose(m[3], [0, 0, 0, 1]):
        raise ValueError(f"not a finite affine (4, 4) matrix: {m.tolist()}")
    lin = m[:3, :3]
    s = float(np.cbrt(np.linalg.det(lin)))
    rot = lin / s if s > 0 else lin
    if not s > 0 or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-12):
        raise ValueError(f"not a similarity (uniform scale > 0 times a rotation): "
                         f"{lin.tolist()}")
    return s, rot, m[:3, 3].copy()


def transform_scene(scene: Scene, m: np.ndarray, name: str | None = None) -> Scene:
    """The scene moved by the similarity m (4, 4) float64 (see `similarity`), with
    everything the image depends on moved or rescaled with it."""
    if scene.animation is not None:
        raise SceneError(f"transform_scene: scene {scene.name!r} has an animation, which it "
                         f"does not move; transform scene.at_frame(f)")
    s, rot, t = split_similarity(m)

    def point(p):
        return tuple((s * (rot @ np.asarray(p, np.float64)) + t).tolist())

    def vector(v, factor=1.0):
        return tuple((factor * (rot @ np.asarray(v, np.float64))).tolist())

    env = scene.environment
    if env.kind == "sky" and not np.allclose(rot @ _UP, _UP, atol=1e-12):
        raise ValueError("a 'sky' environment depends on +y: rotate about the y axis only")
    cam = scene.camera
    camera = Camera(eye=point(cam.eye), target=point(cam.target), up=vector(cam.up),
                    fov_deg=cam.fov_deg, near=None if cam.near is None else s * cam.near)
    return dataclasses.replace(
        scene,
        instances=tuple(Instance(i.mesh, m @ np.asarray(i.transform, np.float64))
                        for i in scene.instances),
        quad_lights=tuple(dataclasses.replace(q, corner=point(q.corner),
                                              edge_u=vector(q.edge_u, s),
                                              edge_v=vector(q.edge_v, s))
                          for q in scene.quad_lights),
        point_lights=tuple(dataclasses.replace(p, position=point(p.position),
                                               intensity=tuple((s * s * np.asarray(
                                                   p.intensity, np.float64)).tolist()))
                           for p in scene.point_lights),
        directional_lights=tuple(dataclasses.replace(d, direction=vector(d.direction))
                                 for d in scene.directional_lights),
        camera=camera,
        name=scene.name if name is None else name)


def trs_matrix(translate=None, rotate_deg=None, scale=None) -> np.ndarray:
    """T @ Rz @ Ry @ Rx @ S as (4, 4) float64; rotate_deg are Euler angles about x, y, z."""
    m = np.eye(4, dtype=TRANSFORM_DTYPE)
    if scale is not None:
        m[:3, :3] = np.diag(np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,)))
    if rotate_deg is not None:
        import trimesh

        r = np.eye(4)
        for axis, deg in zip("xyz", rotate_deg, strict=True):
            r = trimesh.transformations.rotation_matrix(np.radians(deg), _AXES[axis]) @ r
        m = r @ m
    if translate is not None:
        m[:3, 3] = translate
    return m


_AXES = {"x": [1.0, 0.0, 0.0], "y": [0.0, 1.0, 0.0], "z": [0.0, 0.0, 1.0]}
