"""What the driver and the shards say to each other: plain dataclasses, light to import.

The driver (coordinator, pool, placement) imports this module and never the shard's own
modules, which pull in Embree, numba and ONNX Runtime: a driver that holds no geometry
should not pay for the libraries that trace it either."""

from __future__ import annotations

from dataclasses import dataclass

from nprt.scene.model import Mesh
from nprt.workers.passes import Pass
from nprt.workers.settings import RenderSettings

EVERYWHERE = -1  # owner of an instance whose mesh is replicated on every shard


@dataclass(frozen=True)
class ShardConfig:
    """settings: those the pool was started with (placement, warm-up); each call brings
    the settings of the job it belongs to."""

    shard_id: int
    k: int
    settings: RenderSettings


@dataclass(frozen=True)
class MeshRequest:
    """Meshes a shard loads itself, on its own node, from the scene store: the driver
    sends this (a few hundred bytes), never the geometry. indices: mesh indices."""

    source: object  # nprt.scene.store.MeshSource
    indices: tuple[int, ...]

    def load(self) -> dict[int, Mesh]:
        return self.source.load_meshes(self.indices)


@dataclass(frozen=True)
class WorkItem:
    """One pass's share of a call: its camera rays (generate) and/or `n_parcels` of the
    call's parcel arguments, in order. token: the pass attempt (a re-run gets a new one)."""

    token: int
    pass_: Pass
    generate: bool
    n_parcels: int


@dataclass
class Manifest:
    """The small part of a call's result that the coordinator reads."""

    shard: int
    counts: dict[int, list[int]]  # token -> (k,) rays + shadow rays sent to each shard
    busy_s: float = 0.0  # wall time of the call inside the shard
    bytes_in: int = 0  # ray bytes the call received
    bytes_out: int = 0  # ray bytes it sent
