"""What every shard holds besides its own geometry: the instance table with each
instance's owner, the lights, camera and materials. Built once per frame by a Ray task
(`nprt.workers.runtime.remote.build_world`), so its BVH is built off the driver; geometry travels
separately, per shard."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nprt.scene.model import Camera, Material, Scene
from nprt.workers.runtime.protocol import EVERYWHERE
from nprt.workers.traversal.toplevel import InstanceTable
from nprt.workers.wavefront.lights import LightSet


@dataclass(frozen=True, eq=False)
class ShardWorld:
    """owner : (m,) int32 shard of each instance, or EVERYWHERE."""

    name: str
    table: InstanceTable
    owner: np.ndarray
    lights: LightSet
    camera: Camera
    materials: tuple[Material, ...]
    mesh_names: tuple[str, ...]

    @classmethod
    def build(cls, scene: Scene, owner: np.ndarray) -> ShardWorld:
        return cls(scene.name, InstanceTable(scene), np.asarray(owner, np.int32),
                   LightSet(scene), scene.camera, scene.materials,
                   tuple(m.name for m in scene.meshes))

    def local_instances(self, shard: int) -> np.ndarray:
        """(k,) int32 instances intersected on `shard`: its own plus replicated ones."""
        return np.flatnonzero((self.owner == shard) | (self.owner == EVERYWHERE)).astype(np.int32)
