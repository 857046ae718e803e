"""Partitioning objects (a base mesh with its instances) across K shards, balanced by bytes;
with more shards than meshes, a mesh's instances are split into spatially coherent groups.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np

from nprt.scene.errors import SceneError
from nprt.scene.model import Scene, instance_world_bounds
from nprt.scene.workload import instance_work

SHARD_DTYPE = np.int32


@dataclass(frozen=True, eq=False)
class Partition:
    """Which shard owns each instance, and which base meshes each shard holds.

    instance_shard : (n_instances,) int32, owning shard of each instance
    shard_meshes   : per shard, the sorted mesh indices it holds
    shard_bytes    : (k,) int64, geometry bytes per shard (each held mesh counted once)
    """

    k: int
    instance_shard: np.ndarray
    shard_meshes: tuple[tuple[int, ...], ...]
    shard_bytes: np.ndarray

    @property
    def max_shard_bytes(self) -> int:
        """The most geometry memory any one shard holds (the paper's "most memory among nodes")."""
        return int(self.shard_bytes.max())

    def shard_instances(self, shard: int) -> np.ndarray:
        """(m,) int64 indices of the instances owned by `shard`, ascending."""
        return np.flatnonzero(self.instance_shard == shard)

    def mesh_shards(self, mesh: int) -> tuple[int, ...]:
        """The shards holding base mesh `mesh` (several when its instances were split)."""
        return tuple(s for s, held in enumerate(self.shard_meshes) if mesh in held)

    def summary(self) -> dict:
        mean = float(self.shard_bytes.mean())
        held = [m for ms in self.shard_meshes for m in ms]
        return {
            "k": self.k,
            "shard_bytes": self.shard_bytes.tolist(),
            "max_shard_bytes": self.max_shard_bytes,
            "total_shard_bytes": int(self.shard_bytes.sum()),
            "imbalance": round(self.max_shard_bytes / mean, 4) if mean > 0 else 1.0,
            "instances_per_shard": np.bincount(self.instance_shard, minlength=self.k).tolist(),
            "meshes_per_shard": [len(ms) for ms in self.shard_meshes],
            "split_meshes": sorted({m for m in held if held.count(m) > 1}),
        }


def partition(scene: Scene, k: int, replicated=()) -> Partition:
    """Assign every instance to one of k shards, balancing the bytes of the meshes held.

    Objects go largest-first to the shard with the fewest bytes so far. When k exceeds the
    number of instanced meshes, the meshes with the most estimated ray work per piece
    (nprt.scene.workload: the camera's view their instances cover) are split into more
    pieces, each piece a spatially coherent group from recursive median bisection of the
    instance centres along the longest axis. Every shard gets at least one instance.

    replicated: mesh indices every shard will hold (placement's choice for meshes too light
    to be worth forwarding rays to): they take no piece, every shard holds them, and their
    instances are recorded on shard 0 (the placement owns them everywhere). Ignored where
    the other meshes have fewer than k instances.
    """
    n = len(scene.instances)
    if isinstance(k, bool) or not isinstance(k, int | np.integer) or k < 1:
        raise SceneError(f"partition: shard count must be an integer >= 1, got {k!r}")
    if k > n:
        raise SceneError(
            f"partition: cannot give {k} shards at least one instance each; "
            f"scene {scene.name!r} has only {n} instances (use k <= {n})"
        )
    inst_mesh = np.asarray(scene.instance_mesh, dtype=np.int64)
    counts = np.bincount(inst_mesh, minlength=len(scene.meshes))
    nbytes = np.array([m.nbytes for m in scene.meshes], dtype=np.int64)
    everywhere = np.isin(np.arange(len(scene.meshes)), np.asarray(replicated, np.int64))
    if counts[~everywhere].sum() < k:
        everywhere[:] = False
    used = np.flatnonzero(counts * ~everywhere)
    work = np.bincount(inst_mesh, weights=instance_work(scene), minlength=len(scene.meshes))
    pieces = _piece_counts(used, counts, nbytes, work, int(k))
    centres = instance_world_bounds(scene).mean(axis=1)  # (n, 3) float64
    # Instances grouped by mesh, ascending within a mesh: one sort, not a scan per mesh.
    by_mesh = np.argsort(inst_mesh, kind="stable")
    ends = np.cumsum(counts)

    items = []  # (mesh, piece, instance indices)
    for m in used:
        idx = by_mesh[ends[m] - counts[m]:ends[m]]
        for p, group in enumerate(_bisect(centres, idx, pieces[m])):
            items.append((int(m), p, group))
    items.sort(key=lambda it: (-nbytes[it[0]], it[0], it[1]))

    instance_shard = np.empty(n, dtype=SHARD_DTYPE)
    held: list[set[int]] = [set() for _ in range(k)]
    load = np.zeros(k, dtype=np.int64)
    for m, _, group in items:
        # There are at least k items and every mesh has bytes, so the first k items land on
        # the k distinct empty shards (load 0, argmin takes the first): none stays empty.
        s = int(np.argmin(load))
        instance_shard[group] = s
        held[s].add(m)
        load[s] += nbytes[m]
    for m in np.flatnonzero(everywhere & (counts > 0)):
        instance_shard[inst_mesh == m] = 0
        for h in held:
            h.add(int(m))
        load += nbytes[m]
    instance_shard.setflags(write=False)
    load.setflags(write=False)
    return Partition(int(k), instance_shard, tuple(tuple(sorted(h)) for h in held), load)


def _piece_counts(used: np.ndarray, counts: np.ndarray, nbytes: np.ndarray,
                  work: np.ndarray, k: int) -> dict:
    """Pieces per instanced mesh summing to max(k, len(used)): extra pieces go, one at a time,
    to the mesh with the most work per piece (work: (meshes,) float64; ties: more instances
    per piece, more bytes, then lower index). A mesh is cut into at most one piece per
    instance."""
    pieces = {int(m): 1 for m in used}
    heap = [(-float(work[m]), -float(counts[m]), -int(nbytes[m]), int(m))
            for m in used if counts[m] > 1]
    heapq.heapify(heap)
    for _ in range(k - len(used)):
        _, _, neg_bytes, m = heapq.heappop(heap)  # never empty: k <= number of instances
        pieces[m] += 1
        if pieces[m] < counts[m]:
            heapq.heappush(heap, (-work[m] / pieces[m], -counts[m] / pieces[m], neg_bytes, m))
    return pieces


def _bisect(centres: np.ndarray, idx: np.ndarray, parts: int) -> list[np.ndarray]:
    """Split instance indices into `parts` spatially coherent groups of near-equal size.

    centres : (n, 3) float64 world centres of all instances; idx : (m,) int64, m >= parts
    """
    if parts == 1:
        return [idx]
    c = centres[idx]
    axis = int(np.argmax(np.ptp(c, axis=0)))
    order = idx[np.argsort(c[:, axis], kind="stable")]
    left = parts // 2
    cut = int(np.clip(round(len(idx) * left / parts), left, len(idx) - (parts - left)))
    return _bisect(centres, order[:cut], left) + _bisect(centres, order[cut:], parts - left)
