"""Ray batches: frozen struct-of-arrays named by the stage that produces them.

Every field has an explicit dtype; `nbytes` (the sum of the arrays' nbytes) is
what the transfer statistics count. Also the one rule that orders hit records
(`precedes`), so the reference and every shard count pick the same hit on a tie.

Origins travel as float64 (ORIGIN_DTYPE): a float32 world point is only good to
ulp(|p|) / 2, 1/256 at 1e5 and 0.5 at 1e7, so a scene far from the origin would lose
its small shadows however well the spawn offset is chosen. float64 keeps them to
1e-16 relative (2e-9 at 1e7) for 12 more bytes per ray; see workers/kernels/offset.py for the
alternatives measured.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

# Hit record sentinels in `hit_inst` (int32): no hit yet (NO_HIT), or a quad light
# (LIGHT_BASE - light index); tie ranks of hit_inst values (see kernels/records.py, which
# holds the compiled folds of the same order).
from nprt.workers.kernels.records import LIGHT_BASE, NO_HIT, RANK_LIGHT0, RANK_NO_HIT

# Ray kinds, stored in RayBatch.kind (uint8).
from nprt.workers.runtime.protocol import KIND_NAMES, PRIMARY, SECONDARY, SHADOW  # noqa: F401

# Precision policy of the wire format: origins float64, everything else float32 or less.
ORIGIN_DTYPE = np.float64


def tie_rank(hit_inst: np.ndarray) -> np.ndarray:
    """(n,) int32 hit_inst -> (n,) int64 rank: the order of hits at equal t (quad lights
    first, in light order, then instances in instance order; "no hit" last, so any hit
    at or before tmax replaces it)."""
    h = np.asarray(hit_inst, np.int64)
    return np.where(h >= 0, h, np.where(h == NO_HIT, RANK_NO_HIT, RANK_LIGHT0 + LIGHT_BASE - h))


def precedes(t_a, inst_a, prim_a, t_b, inst_b, prim_b) -> np.ndarray:
    """(n,) bool: hit a comes before hit b in the global order, the one rule every fold
    of hit records follows: smaller t (float32, as stored in the record); on equal t the
    lower `tie_rank`, then the lower primitive. t (n,) float32, inst, prim (n,) int32."""
    t_a, t_b = np.asarray(t_a, np.float32), np.asarray(t_b, np.float32)
    r_a, r_b = tie_rank(inst_a), tie_rank(inst_b)
    return (t_a < t_b) | ((t_a == t_b) & ((r_a < r_b) | ((r_a == r_b) & (prim_a < prim_b))))


def _check(name: str, arr: np.ndarray, n: int, width: int | None, dtype) -> None:
    want = (n,) if width is None else (n, width)
    if arr.shape != want or arr.dtype != dtype:
        raise ValueError(
            f"{name}: expected shape {want} dtype {np.dtype(dtype)}, got {arr.shape} {arr.dtype}"
        )


class _Batch:
    """Shared struct-of-arrays behaviour; subclasses are frozen dataclasses."""

    _SPEC: dict = {}
    _ROW_BYTES = 0  # bytes of one row over all columns, set from _SPEC below

    # Columns are read through the instance __dict__, which holds exactly the dataclass
    # fields in _SPEC order: calling dataclasses.fields() on every take/replace cost ~5 %
    # of a render, and a getattr per column most of a small batch's glue.

    def __post_init__(self):
        cols = self.__dict__
        n = len(cols["pixel"])
        for name, (width, dtype) in self._SPEC.items():
            _check(name, cols[name], n, width, dtype)

    def __len__(self) -> int:
        return self.__dict__["pixel"].shape[0]

    @property
    def nbytes(self) -> int:
        """Bytes of the columns: every column has its spec's dtype and width (checked when
        the batch is made), so this is rows x `row_bytes`."""
        return len(self) * self._ROW_BYTES

    @classmethod
    def _trusted(cls, cols: dict):
        """A batch of columns already checked (rows of checked batches): no validation,
        which costs more than the copy itself for small batches."""
        batch = object.__new__(cls)
        batch.__dict__.update(cols)  # frozen: fields are set past __setattr__
        return batch

    def take(self, index: np.ndarray):
        """Rows selected by a bool mask or an index array. A mask that keeps every row
        gives this batch itself: batches are immutable, so their rows may be shared."""
        index = np.asarray(index)
        if index.dtype == bool:  # one nonzero scan, not one per column
            index = np.flatnonzero(index)
            if len(index) == len(self):
                return self
        # np.take along axis 0, not arr[index]: 3-4x faster on the (n, 3) columns (numpy's
        # fancy indexing of a 2-D array takes its general N-d path); same rows, same bytes.
        return self._trusted({name: np.take(arr, index, axis=0)
                              for name, arr in self.__dict__.items()})

    def rows(self, start: int, stop: int):
        """Rows start:stop as views of this batch's columns (no copy)."""
        return self._trusted({name: arr[start:stop] for name, arr in self.__dict__.items()})

    def replace(self, **changes):
        n = len(self)
        for name, arr in changes.items():
            width, dtype = self._SPEC[name]
            _check(name, arr, n, width, dtype)
        return self._trusted({**self.__dict__, **changes})

    @classmethod
    def gather(cls, parts: list):
        """One batch of the rows of parts, [(batch, rows)] in order, where rows is an index
        array, a bool mask or None (every row): one copy per column, where a take then a
        concat would copy twice. A single part whose rows are all of its batch gives that
        batch itself (batches are immutable)."""
        parts = [(b, _rows(b, r)) for b, r in parts if b is not None]
        parts = [(b, r) for b, r in parts if (len(b) if r is None else len(r))]
        if not parts:
            return cls.empty()
        if len(parts) == 1:
            b, r = parts[0]
            return b if r is None else b.take(r)
        return cls._trusted(gather_columns(parts, cls._SPEC))

    @classmethod
    def concat(cls, batches: list):
        batches = [b for b in batches if b is not None and len(b)]
        if not batches:
            return cls.empty()
        if len(batches) == 1:
            return batches[0]
        return cls._trusted({name: np.concatenate([b.__dict__[name] for b in batches])
                             for name in cls._SPEC})

    @classmethod
    def empty(cls):
        """The batch of no rows (one per class: batches are immutable)."""
        made = cls.__dict__.get("_EMPTY")
        if made is None:
            made = cls(**{name: np.zeros((0,) if w is None else (0, w), dtype=dt)
                          for name, (w, dt) in cls._SPEC.items()})
            cls._EMPTY = made
        return made


def _rows(batch, rows):
    """rows of batch as an index array, or None for every row in order."""
    if rows is None:
        return None
    rows = np.asarray(rows)
    if rows.dtype == bool:
        rows = np.flatnonzero(rows)
        if len(rows) == len(batch):
            return None
    return rows


def gather_columns(parts: list, names) -> dict:
    """{name: column} of the rows of parts [(batch, rows (r,) int index array or None: all)]
    in order, for the columns named (any subset of the batches' spec): each column made
    once at its full length and filled part by part."""
    spec = parts[0][0]._SPEC
    sizes = [len(b) if r is None else len(r) for b, r in parts]
    n = sum(sizes)
    out = {}
    for name in names:
        width, dtype = spec[name]
        col = np.empty((n,) if width is None else (n, width), dtype)
        a = 0
        for (b, r), m in zip(parts, sizes, strict=True):
            if r is None:
                col[a:a + m] = b.__dict__[name]
            else:  # mode "clip": take into `out` without its bounds-checked buffer
                np.take(b.__dict__[name], r, axis=0, out=col[a:a + m], mode="clip")
            a += m
        out[name] = col
    return out


_RAY_SPEC = {
    "origin": (3, ORIGIN_DTYPE),
    "direction": (3, np.float32),
    "tmax": (None, np.float32),
    "throughput": (3, np.float32),
    "pixel": (None, np.uint32),
    "sample": (None, np.uint32),
    "depth": (None, np.uint8),
    "kind": (None, np.uint8),
    "visited": (None, np.uint64),
    "pdf_prev": (None, np.float32),  # solid-angle pdf of the BSDF sample that made this ray (MIS)
    "hit_inst": (None, np.int32),  # closest hit so far: instance, or LIGHT_BASE - light
    "hit_prim": (None, np.int32),
    "hit_u": (None, np.float32),
    "hit_v": (None, np.float32),
    "hops": (None, np.uint8),  # shard-to-shard transfers so far
    "flags": (None, np.uint8),  # traversal state bits, see FLAG_*
}

# RayBatch.flags bits (proxy traversal state; exact rays keep 0).
FLAG_EXACT = 1  # fell back to exact forwarding (uncertain prediction or a miss at the target)
FLAG_TARGETED = 2  # sent to the shard a proxy predicted; the hit there is final
FLAG_SHADE = 4  # closest hit is final; sent to the hit's owner only to be shaded
FLAG_INTERNAL = 8  # with FLAG_TARGETED: the prediction came from inside the hit's box


@dataclass(frozen=True, eq=False)
class RayBatch(_Batch):
    """Camera and BSDF rays looking for their closest hit (kind PRIMARY or SECONDARY).

    origin (n,3) f64, direction (n,3) f32, tmax (n,) f32 (closest hit so far),
    throughput (n,3) f32, pixel (n,) u32, sample (n,) u32, depth (n,) u8,
    kind (n,) u8, visited (n,) u64 shard bitmask, pdf_prev (n,) f32,
    hit_inst/hit_prim (n,) i32, hit_u/hit_v (n,) f32, hops (n,) u8, flags (n,) u8 (FLAG_* bits).
    """

    _SPEC = _RAY_SPEC
    origin: np.ndarray
    direction: np.ndarray
    tmax: np.ndarray
    throughput: np.ndarray
    pixel: np.ndarray
    sample: np.ndarray
    depth: np.ndarray
    kind: np.ndarray
    visited: np.ndarray
    pdf_prev: np.ndarray
    hit_inst: np.ndarray
    hit_prim: np.ndarray
    hit_u: np.ndarray
    hit_v: np.ndarray
    hops: np.ndarray
    flags: np.ndarray


_SHADOW_SPEC = {
    "origin": (3, ORIGIN_DTYPE),
    "direction": (3, np.float32),
    "tmax": (None, np.float32),
    "contribution": (3, np.float32),  # radiance added to `pixel` if unoccluded
    "pixel": (None, np.uint32),
    "visited": (None, np.uint64),
    "hops": (None, np.uint8),
}


@dataclass(frozen=True, eq=False)
class ShadowRayBatch(_Batch):
    """Next-event rays: contribution (n,3) f32 lands on pixel (n,) u32 unless occluded
    before tmax (n,) f32. origin (n,3) f64, direction (n,3) f32, visited (n,) u64,
    hops (n,) u8."""

    _SPEC = _SHADOW_SPEC
    origin: np.ndarray
    direction: np.ndarray
    tmax: np.ndarray
    contribution: np.ndarray
    pixel: np.ndarray
    visited: np.ndarray
    hops: np.ndarray


for _cls in (RayBatch, ShadowRayBatch):  # _Batch walks _SPEC in place of the fields
    if [f.name for f in fields(_cls)] != list(_cls._SPEC):
        raise TypeError(f"{_cls.__name__}: _SPEC and the dataclass fields differ")
    _cls._ROW_BYTES = sum(np.dtype(dt).itemsize * (w or 1) for w, dt in _cls._SPEC.values())
