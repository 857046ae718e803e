"""Dynamic scenes: per-frame instance transforms and light parameters.

An `Animation` holds every frame's values of what moves, sampled once when the scene is
loaded (from JSON keyframes, `nprt.scene.animation_io`, or glTF channels, `nprt.scene.gltf_anim`),
so `scene_at(scene, f)` is an array copy: meshes, materials and the camera are shared,
never copied. Only instance transforms and lights move; geometry never does, so a shard
keeps its meshes and a proxy (keyed by mesh content) stays valid on every frame.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from nprt.scene.errors import SceneError
from nprt.scene.model import TRANSFORM_DTYPE, Instances, Scene, validate_transforms

INTERPOLATIONS = ("linear", "step")
MAX_FRAMES = 100_000  # a bound on what loading samples (frames x animated instances)


@dataclass(frozen=True, eq=False)
class Animation:
    """frames : N >= 1
    instances  : (a,) int64 indices of the animated instances, ascending
    transforms : (N, a, 4, 4) float64 local -> world of each of them on each frame
    quad_lights, point_lights, directional_lights : N tuples of the scene's lights on each
        frame, or None where those lights do not move"""

    frames: int
    instances: np.ndarray
    transforms: np.ndarray
    quad_lights: tuple | None = None
    point_lights: tuple | None = None
    directional_lights: tuple | None = None

    def __post_init__(self):
        if not 1 <= self.frames <= MAX_FRAMES:
            raise SceneError(f"animation.frames: must lie in [1, {MAX_FRAMES}], got "
                             f"{self.frames!r}")
        idx = np.asarray(self.instances, np.int64)
        xf = np.asarray(self.transforms, TRANSFORM_DTYPE)
        if xf.shape != (self.frames, len(idx), 4, 4):
            raise SceneError(f"animation: transforms must have shape ({self.frames}, "
                             f"{len(idx)}, 4, 4), got {xf.shape}")
        for name in ("quad_lights", "point_lights", "directional_lights"):
            per_frame = getattr(self, name)
            if per_frame is not None and len(per_frame) != self.frames:
                raise SceneError(f"animation: {name} has {len(per_frame)} frames, "
                                 f"not {self.frames}")
        validate_transforms(xf.reshape(-1, 4, 4), lambda j: (
            f"animation: instance {int(idx[j % len(idx)])} on frame {j // len(idx)}"))
        idx.setflags(write=False)
        xf.setflags(write=False)
        object.__setattr__(self, "instances", idx)
        object.__setattr__(self, "transforms", xf)


def check_frame(scene, frame: int) -> int:
    """frame as an int in [0, scene.frames), or a SceneError naming it."""
    n = scene.frames
    if isinstance(frame, bool) or not isinstance(frame, int | np.integer) or \
            not 0 <= frame < n:
        raise SceneError(f"frame {frame!r} out of range: scene {scene.name!r} has {n} "
                         f"frame{'s' if n != 1 else ''} (0 to {n - 1})")
    return int(frame)


def _replace(scene, **changes):
    """dataclasses.replace of a Scene or SceneMeta; a Scene's meshes, validated when it
    was made and shared unchanged, are not checked again."""
    if isinstance(scene, Scene):
        changes["check_meshes"] = False
    return dataclasses.replace(scene, **changes)


def with_animation(scene, anim: Animation | None):
    """`scene` (a Scene or SceneMeta) carrying `anim`, its instances and lights unchanged."""
    return _replace(scene, animation=anim)


def scene_at(scene, frame: int):
    """The scene (a Scene, or a `nprt.scene.meta.SceneMeta`: no mesh is read) on `frame`:
    the same meshes, materials and camera (shared, not copied), this frame's instance
    transforms and lights. A scene without animation has one frame, itself. The result
    keeps the animation, so any frame is reachable from any."""
    frame = check_frame(scene, frame)
    anim = scene.animation
    if anim is None:
        return scene
    xf = np.array(scene.instance_transform)  # (m, 4, 4) float64
    xf[anim.instances] = anim.transforms[frame]
    moved = {"instances": Instances(scene.instance_mesh, xf)}
    for name in ("quad_lights", "point_lights", "directional_lights"):
        per_frame = getattr(anim, name)
        if per_frame is not None:
            moved[name] = per_frame[frame]
    return _replace(scene, **moved)


def frame_range(text: str, frames: int) -> range:
    """'A:B' (inclusive), 'A' or ':' as a range of frames within [0, frames)."""
    first, sep, last = str(text).partition(":")
    try:
        a = int(first) if first.strip() else 0
        b = (int(last) if last.strip() else frames - 1) if sep else a
    except ValueError:
        raise SceneError(f"frames {text!r}: want A:B (first and last frame, inclusive), "
                         f"A, or ':' for all") from None
    if not 0 <= a <= b < frames:
        raise SceneError(f"frames {text!r}: must satisfy 0 <= A <= B < {frames} "
                         f"(the scene has {frames} frames)")
    return range(a, b + 1)


# ------------------------------------------------------------------ sampling keyframes


def _segments(times: np.ndarray, at: np.ndarray):
    """For each t in `at`, the key index i with times[i] <= t < times[i + 1] (clamped to
    the ends) and the fraction (0..1) of the way to key i + 1."""
    i = np.clip(np.searchsorted(times, at, side="right") - 1, 0, len(times) - 1)
    j = np.minimum(i + 1, len(times) - 1)
    span = times[j] - times[i]
    with np.errstate(invalid="ignore", divide="ignore"):
        alpha = np.where(span > 0, (at - times[i]) / np.where(span > 0, span, 1.0), 0.0)
    return i, j, np.clip(alpha, 0.0, 1.0)


def sample_linear(times, values, at, interpolation: str = "linear") -> np.ndarray:
    """Sample a keyframed vector track. times (k,) ascending; values (k, d); at (n,) ->
    (n, d) float64: lerp between keys ("linear") or the last key at or before ("step"),
    the end keys held outside the keyed range."""
    times, values = np.asarray(times, np.float64), np.asarray(values, np.float64)
    i, j, alpha = _segments(times, np.asarray(at, np.float64))
    if interpolation == "step":
        return values[i]
    return values[i] + alpha[:, None] * (values[j] - values[i])


def sample_rotation(times, quats, at, interpolation: str = "linear") -> np.ndarray:
    """Sample a rotation track. quats (k, 4) unit quaternions w, x, y, z; returns (n, 4):
    spherical linear interpolation along the shorter arc, or "step"."""
    times, q = np.asarray(times, np.float64), np.asarray(quats, np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    i, j, alpha = _segments(times, np.asarray(at, np.float64))
    if interpolation == "step":
        return q[i]
    q0, q1 = q[i], q[j]
    dot = np.einsum("ij,ij->i", q0, q1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin = np.sin(theta)
    near = sin < 1e-9  # (nearly) the same rotation: lerp is exact enough
    safe = np.where(near, 1.0, sin)
    w0 = np.where(near, 1.0 - alpha, np.sin((1.0 - alpha) * theta) / safe)
    w1 = np.where(near, alpha, np.sin(alpha * theta) / safe)
    out = w0[:, None] * q0 + w1[:, None] * q1
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def trs_matrices(t: np.ndarray, q: np.ndarray, s: np.ndarray) -> np.ndarray:
    """T @ R(q) @ S as (n, 4, 4) float64 from translations (n, 3), quaternions (n, 4)
    w, x, y, z (normalised here) and scales (n, 3)."""
    q = np.asarray(q, np.float64)
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    rot = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], axis=1)  # (n, 3, 3)
    out = np.zeros((len(q), 4, 4), TRANSFORM_DTYPE)
    out[:, :3, :3] = rot * np.asarray(s, np.float64)[:, None, :]
    out[:, :3, 3] = t
    out[:, 3, 3] = 1.0
    return out


def split_trs(m: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(4, 4) affine -> translation (3,), quaternion (4,) w, x, y, z, scale (3,), or a
    SceneError when it has shear (it is not T @ R @ S) or is singular."""
    m = np.asarray(m, np.float64)
    lin = m[:3, :3]
    scale = np.linalg.norm(lin, axis=0)
    if not (scale > 0).all():
        raise SceneError(f"{where}: transform is singular")
    if np.linalg.det(lin) < 0:
        scale[0] = -scale[0]  # a mirror: fold it into the scale
    rot = lin / scale
    if not np.allclose(rot.T @ rot, np.eye(3), atol=1e-6):
        raise SceneError(f"{where}: transform has shear, so it cannot be interpolated; "
                         f"give translate/rotate_deg/scale keys")
    # Imported here: trimesh imports Embree, which a render driver reading an animated
    # scene's metadata must not load.
    from trimesh import transformations as tf

    r4 = np.eye(4)
    r4[:3, :3] = rot
    return m[:3, 3].copy(), tf.quaternion_from_matrix(r4), scale
