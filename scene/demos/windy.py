"""The animated demo: the forest over 8 frames, a few trees sliding across the view and
the sun panel sweeping overhead. Geometry never changes between frames, so a renderer
keeps its meshes and proxies and swaps only the instance table and lights."""

from __future__ import annotations

import dataclasses

import numpy as np

from nprt.scene.animation import Animation
from nprt.scene.demos import forest
from nprt.scene.model import Scene

FRAMES = 8
MOVING = 4  # trees that move


def build(size: str, seed: int) -> Scene:
    scene = forest.build(size, seed)
    half = forest.SIZES[size]["half"]
    xf = scene.instance_transform
    # The trees nearest the camera's target line move: they are in view on every frame.
    cam = np.asarray(scene.camera.target)
    trees = np.arange(1, len(xf))  # instance 0 is the ground
    near = trees[np.argsort(np.linalg.norm(xf[trees, :3, 3] - cam, axis=1))[:MOVING]]
    idx = np.sort(near)
    t = np.linspace(0.0, 1.0, FRAMES)  # (N,) animation time
    moved = np.repeat(np.array(xf[idx])[None], FRAMES, axis=0)  # (N, a, 4, 4)
    side = np.where(np.arange(MOVING) % 2 == 0, 1.0, -1.0)  # alternate directions
    moved[:, :, 0, 3] += (0.25 * half * side[None, :]) * t[:, None]
    moved[:, :, 2, 3] += 0.1 * half * t[:, None]
    sun = scene.quad_lights[0]
    sweep = np.linspace(-0.6 * half, 0.6 * half, FRAMES)  # the sun crosses the sky in x
    quads = tuple((dataclasses.replace(sun, corner=(float(sun.corner[0] + dx - 0.4 * half),
                                                    *sun.corner[1:])),) for dx in sweep)
    anim = Animation(FRAMES, idx, moved, quad_lights=quads)
    animated = dataclasses.replace(scene, animation=anim, name=f"windy-{size}",
                                   check_meshes=False)
    return animated.at_frame(0)
