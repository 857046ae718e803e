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
    with_animation,
)
from nprt.scene.errors import SceneError
from nprt.scene.transform import trs_matrix

# Fields each kind of light may key, by its field in `lights` and the Scene's.
LIGHT_FIELDS = {
    "quads": ("quad_lights", ("corner", "edge_u", "edge_v", "radiance")),
    "points": ("point_lights", ("position", "intensity")),
    "directionals": ("directional_lights", ("direction", "irradiance")),
}


def animate(scene, spec: schema.AnimationSpec):
    """`scene` (a Scene or a `nprt.scene.meta.SceneMeta`: its instances and lights the static
    poses) with `spec`'s animation, as its frame 0. Reads only the instance table and
    lights, never a mesh. On a keyed frame a pose is the key's exactly."""
    n, interp = spec.frames, spec.interpolation
    at = np.arange(n, dtype=np.float64)
    idx = np.array(sorted(spec.instances), np.int64)
    xf = np.zeros((n, len(idx), 4, 4))
    for j, inst in enumerate(idx):
        where = f"animation.instances[{inst}]"
        if inst >= len(scene.instances):
            raise SceneError(f"{where}: no such instance (the scene has "
                             f"{len(scene.instances)})")
        keys = spec.instances[int(inst)]
        times = _key_frames(keys, n, where)
        mats = np.array([np.asarray(k.transform, np.float64) if k.transform is not None
                         else trs_matrix(k.translate, k.rotate_deg, k.scale) for k in keys])
        if interp == "step":  # the earlier key's matrix as is: nothing to decompose
            xf[:, j] = mats[np.clip(np.searchsorted(times, at, side="right") - 1, 0, None)]
            continue
        poses = [split_trs(m, f"{where} key at frame {k.frame}")
                 for m, k in zip(mats, keys, strict=True)]
        t, q, s = (np.array([p[c] for p in poses]) for c in range(3))
        xf[:, j] = trs_matrices(sample_linear(times, t, at, interp),
                                sample_rotation(times, q, at, interp),
                                sample_linear(times, s, at, interp))
        xf[times.astype(np.int64), j] = mats  # keyed frames: no decompose/recompose rounding
    lights = {}
    for kind, (attr, fields) in LIGHT_FIELDS.items():
        tracks = getattr(spec.lights, kind)
        if tracks:
            lights[attr] = _light_frames(getattr(scene, attr), tracks, fields, n, interp,
                                         f"animation.lights.{kind}")
    out = with_animation(scene, Animation(n, idx, xf, **lights))
    for fr in range(1, n) if lights else ():  # refuse a bad light on any frame now
        scene_at(out, fr)
    return scene_at(out, 0)


def animation_doc(scene) -> dict | None:
    """`scene.animation` as the JSON scene's "animation" (`schema.AnimationSpec`): every
    frame keyed, `step` interpolation, instance poses as matrices, so loading it back gives
    exactly the same frames. None for a scene without animation."""
    anim = scene.animation
    if anim is None:
        return None
    n = anim.frames
    doc = {"frames": n, "interpolation": "step",
           "instances": {str(int(inst)): [
               {"frame": f, "transform": anim.transforms[f, j].tolist()} for f in range(n)]
               for j, inst in enumerate(anim.instances)},
           "lights": {}}
    for kind, (attr, fields) in LIGHT_FIELDS.items():
        per_frame = getattr(anim, attr)
        if per_frame is None:
            continue
        tracks = {str(li): [{"frame": f, **{k: [float(x) for x in getattr(per_frame[f][li], k)]
                                           for k in fields}} for f in range(n)]
                  for li in range(len(per_frame[0]))
                  if any(per_frame[f][li] != per_frame[0][li] for f in range(n))}
        if tracks:
            doc["lights"][kind] = tracks
    return doc


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
