"""What the driver and the shards say to each other: plain dataclasses, light to import.

The driver (coordinator, pool, placement) imports this module and never the shard's own
modules, which pull in Embree, numba and ONNX Runtime: a driver that holds no geometry
should not pay for the libraries that trace it either. Ray batches appear here only as
opaque fields; the driver creates parcels that carry orders, never rays."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np

from nprt.scene.model import Mesh
from nprt.workers.passes import Pass
from nprt.workers.settings import RenderSettings

EVERYWHERE = -1  # owner of an instance whose mesh is replicated on every shard
# Ray kinds, as stored in RayBatch.kind (uint8) and named in every statistic.
PRIMARY, SECONDARY, SHADOW = 0, 1, 2
KIND_NAMES = ("primary", "secondary", "shadow")


@dataclass(frozen=True)
class ShardConfig:
    """settings: those the pool was started with (placement, warm-up); each job brings
    its own settings (`ShardActor.begin`)."""

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


@dataclass
class Parcel:
    """Work for one shard: rays other shards sent it, and/or orders to generate the camera
    rays of passes. `credits` is the termination weight (pass index -> exact fraction of
    1) that the parcel carries for each pass it holds rays or orders of: a pass is done
    when the coordinator has all of its weight back (weight-throwing termination).

    epoch: the job run it belongs to (a parcel of an older run is dropped on arrival);
    source: (shard, step, seconds into that step when it left, None: at its end) that made
    it, for the call trace; None for an order."""

    epoch: int
    credits: dict[int, Fraction]
    rays: object = None  # nprt.workers.wavefront.batch.RayBatch or None
    shadow: object = None  # nprt.workers.wavefront.batch.ShadowRayBatch or None
    orders: tuple[Pass, ...] = ()
    # Camera rays by name: (pixel (n,) uint32, sample (n,) uint32), 8 bytes a ray instead
    # of a RayBatch row's 92; the receiver makes the rays (a function of pixel, sample, seed).
    camera: tuple | None = None
    source: tuple[int, int, float | None] | None = None
    sent_at: float = field(default_factory=time.time)  # wall clock, for transfer wait

    def _parts(self):
        return [b for b in (self.rays, self.shadow, *(self.camera or ())) if b is not None]

    @property
    def nbytes(self) -> int:
        return sum(b.nbytes for b in self._parts())

    @property
    def n_rays(self) -> int:
        return sum(len(b) for b in (self.rays, self.shadow) if b is not None) + \
            (len(self.camera[0]) if self.camera is not None else 0)

    def __reduce__(self):
        # Each batch travels as one buffer, not as 16 arrays: Ray's serializer pays per
        # array on both sides (0.1-0.6 ms a parcel, bench/README.md "Where the extra CPU
        # of K shards goes"), and the receiver views the columns in place.
        return _rebuild_parcel, (self.epoch, self.credits, _pack(self.rays),
                                 _pack(self.shadow), self.orders, self.camera, self.source,
                                 self.sent_at)


_ALIGN = 8  # bytes: every column starts aligned for its dtype (at most 8 bytes wide)


def sum_credits(credit_maps) -> dict[int, Fraction]:
    """Pass index -> the sum of its weights over credit maps (Parcel.credits): what the
    parcels merged into one step, or into one parcel, carry together."""
    out: dict[int, Fraction] = {}
    for credits in credit_maps:
        for i, w in credits.items():
            out[i] = out.get(i, 0) + w
    return out


def _pack(batch):
    """(class, rows, offsets, (nbytes,) uint8 buffer) of a RayBatch / ShadowRayBatch (any
    class with `_SPEC`, `_trusted`), or None. Columns are copied once, back to back."""
    if batch is None:
        return None
    cols = [np.ascontiguousarray(getattr(batch, name)) for name in batch._SPEC]
    offsets, end = [], 0
    for a in cols:
        offsets.append(end)
        end += -(-a.nbytes // _ALIGN) * _ALIGN
    buf = np.empty(end, np.uint8)
    for a, o in zip(cols, offsets, strict=True):
        buf[o:o + a.nbytes] = a.reshape(-1).view(np.uint8)
    return type(batch), len(batch), offsets, buf


def _writable(a: np.ndarray) -> np.ndarray:
    """`a`, or a copy where it is read-only. Ray hands call arguments over read-only (views
    of the received bytes or of the object store), and numba compiles a kernel again for
    read-only arrays (`readonly array(...)` is another type): the kernels that the shard's
    warm-up compiled for its own writable rays were compiled again, for 15-20 s of CPU per
    shard, inside the first render on a machine whose cache lacked the read-only variants.
    A copy costs a memcpy a parcel (a few tens of us for 5,000 rays)."""
    return a if a.flags.writeable else a.copy()


def _unpack(packed):
    if packed is None:
        return None
    cls, n, offsets, buf = packed
    buf = _writable(buf)
    cols = {}
    for (name, (width, dtype)), o in zip(cls._SPEC.items(), offsets, strict=True):
        shape = (n,) if width is None else (n, width)
        cols[name] = np.frombuffer(buf, dtype, n * (width or 1), o).reshape(shape)
    return cls._trusted(cols)  # the sender's batch was checked; the bytes are the same


def _rebuild_parcel(epoch, credits, rays, shadow, orders, camera, source, sent_at) -> Parcel:
    if camera is not None:
        camera = tuple(_writable(a) for a in camera)
    return Parcel(epoch, credits, _unpack(rays), _unpack(shadow), orders, camera, source,
                  sent_at)


@dataclass
class PollReply:
    """What a shard tells the coordinator since its last poll: the weight of passes whose
    rays ended there, and its running totals for the job (CPU and busy seconds, per phase
    too). incarnation changes when Ray restarts the actor: its state is gone."""

    shard: int
    incarnation: str
    epoch: int | None
    returned: list[tuple[int, Fraction]]  # (pass index, weight) in the order they ended
    steps: int = 0  # wavefront steps run this job
    busy_s: float = 0.0  # wall seconds inside steps
    cpu_s: float = 0.0  # process CPU seconds while the job ran (every thread)
    wavefront_cpu_s: float = 0.0  # of which the wavefront thread's, in its steps
    phase_s: dict = field(default_factory=dict)
    phase_cpu_s: dict = field(default_factory=dict)
    bytes_in: int = 0
    bytes_out: int = 0
    parcels_in: int = 0
    parcels_out: int = 0
    trace: list[dict] = field(default_factory=list)  # new step records (tracing jobs only)
    # Films of finished passes the poll asked for, as `ShardActor.collect` gives them:
    # [(pass index, FilmSums or None, stats dict or None)]
    collected: list = field(default_factory=list)
    idle: bool = False  # no step running and nothing in the inbox when it answered
    at: float = 0.0  # the shard's time.monotonic() when it answered
