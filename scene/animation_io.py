"""JSON keyframes (`schema.AnimationSpec`) -> `nprt.scene.animation.Animation`, every frame
sampled once at load time; errors name the track and key."""

from __future__ import annotations

import dataclasses

import numpy as np

from nprt.scene import schema
from nprt.scene.animation import (
    Animation,
    sample_linear,
    sample_rotation,
    scene_at,
    split_trs,
    trs_matrices,
)
from nprt.scene.errors import SceneError
from nprt.scene.io import trs_matrix
from nprt.scene.model import Scene

# Fields each kind of light may key, by its field in `lights` and the Scene's.
LIGHT_FIELDS = {
    "quads": ("quad_lights", ("corner", "edge_u", "edge_v", "radiance")),
    "points": ("point_lights", ("position", "intensity")),
    "directionals": ("directional_lights", ("direction", "irradiance")),
}


def animate(scene: Scene, spec: schema.AnimationSpec) -> Scene:
    """`scene` (its instances and lights the static poses) with `spec`'s animation, as
    its frame 0."""
    n, interp = spec.frames, spec.interpolation
    at = np.arange(n, dtype=np.float64)
    idx = np.array(sorted(spec.instances), np.int64)
    xf = np.zeros((n, len(idx), 4, 4))
    for j, inst in enumerate(idx):
        where = f"animation.instances[{inst}]"
        if inst >= len(scene.instances):
            raise SceneError(f"{where}: no such instance (the scene has "
                             f"{len(nprt.scene.instances)})")
        keys = spec.instances[int(inst)]
        times = _key_frames(keys, n, where)
        poses = [split_trs(k.transform if k.transform is not None else
                           trs_matrix(k.translate, k.rotate_deg, k.scale),
                           f"{where} key at frame {k.frame}") for k in keys]
        t, q, s = (np.array([p[c] for p in poses]) for c in range(3))
        xf[:, j] = trs_matrices(sample_linear(times, t, at, interp),
                                sample_rotation(times, q, at, interp),
                                sample_linear(times, s, at, interp))
    lights = {}
    for kind, (attr, fields) in LIGHT_FIELDS.items():
        tracks = getattr(spec.lights, kind)
        if tracks:
            lights[attr] = _light_frames(getattr(scene, attr), tracks, fields, n, interp,
                                         f"animation.lights.{kind}")
    anim = Animation(n, idx, xf, **lights)
    out = dataclasses.replace(scene, animation=anim, check_meshes=False)
    for fr in range(1, n) if lights else ():  # refuse a bad light on any frame now
        scene_at(out, fr)
    return scene_at(out, 0)


def _key_frames(keys, n: int, where: str) -> np.ndarray:
    """(k,) float64 the keys' frames, strictly increasing and below n."""
    frames = np.array([k.frame for k in keys], np.float64)
    if frames.max() >= n:
        raise SceneError(f"{where}: key at frame {int(frames.max())} is past the last "
                         f"frame ({n - 1})")
    if (np.diff(frames) <= 0).any():
        raise SceneError(f"{where}: key frames must be strictly increasing, got "
                         f"{[int(f) for f in frames]}")
    return frames


def _light_frames(static: tuple, tracks: dict, fields: tuple, n: int, interp: str,
                  where: str) -> tuple:
    """n tuples of the lights of one kind, those with a track moved."""
    per_frame = [list(static) for _ in range(n)]
    at = np.arange(n, dtype=np.float64)
    for li, keys in sorted(tracks.items()):
        w = f"{where}[{li}]"
        if li >= len(static):
            raise SceneError(f"{w}: no such light (there are {len(static)})")
        times = _key_frames(keys, n, w)
        light = static[li]
        for k in keys:
            other = [f for f in schema.LightKeySpec.model_fields
                     if f != "frame" and f not in fields and getattr(k, f) is not None]
            if other:
                raise SceneError(f"{w} key at frame {k.frame}: {other[0]!r} is not a field of "
                                 f"this light (it has {', '.join(fields)})")
        moved = {}
        for f in fields:
            if any(getattr(k, f) is not None for k in keys):
                values = [getattr(k, f) if getattr(k, f) is not None else getattr(light, f)
                          for k in keys]
                moved[f] = sample_linear(times, values, at, interp)
        for fr in range(n):
            per_frame[fr][li] = dataclasses.replace(
                light, **{f: tuple(float(x) for x in v[fr]) for f, v in moved.items()})
    return tuple(tuple(lights) for lights in per_frame)
