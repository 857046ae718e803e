"""An optional record of every shard call a Coordinator makes: which shard ran it, for which
pass attempts, how long it ran inside the shard, the ray bytes it took in and sent out, and
which earlier calls' outputs it consumed. bench/network/netmodel.py replays it with other node
counts and link speeds.

Cheap by design: a few list appends per call, and parcels are keyed by their ObjectRef's
hex id, so the recorder never holds a reference that would keep a parcel alive.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field


@dataclass
class CallRecord:
    """One `Shard.work` call. Times are seconds since the recorder started (driver clock).

    inputs: (producer call, rays) per parcel consumed, one per (producer, pass attempt);
    input_bytes: the call's bytes_in split over `inputs` in proportion to their rays (a
    parcel's own byte count never reaches the driver)."""

    call: int
    shard: int
    tokens: list[int]
    dispatch_s: float
    inputs: list[tuple[int, int]] = field(default_factory=list)
    input_bytes: list[int] = field(default_factory=list)
    return_s: float | None = None
    busy_s: float = 0.0
    bytes_in: int = 0
    bytes_out: int = 0
    rays_out: list[int] = field(default_factory=list)  # (k,) rays sent to each shard


class TraceRecorder:
    """Fed by the Coordinator at dispatch and at return of every work call."""

    def __init__(self, k: int):
        self.k = k
        self.t0 = time.perf_counter()
        self.calls: list[CallRecord] = []
        self._by_manifest: dict[str, CallRecord] = {}  # manifest ref hex -> its call
        self._producer: dict[str, tuple[int, int]] = {}  # output ref hex -> (call, target)
        self._counts: dict[int, dict] = {}  # call -> its manifest's {token: (k,) rays}

    def on_dispatch(self, shard: int, by_token: dict[int, list], manifest_ref, outs) -> None:
        """by_token: token -> the parcel refs (None: generate camera rays) sent with it."""
        rec = CallRecord(len(self.calls), shard, list(by_token),
                         time.perf_counter() - self.t0)
        for token, refs in by_token.items():
            for ref in refs:
                if ref is None:
                    continue
                producer, target = self._producer[ref.hex()]
                rec.inputs.append((producer, int(self._counts[producer][token][target])))
        for target, ref in enumerate(outs):
            self._producer[ref.hex()] = (rec.call, target)
        self._by_manifest[manifest_ref.hex()] = rec
        self.calls.append(rec)

    def on_return(self, manifest_ref, manifest) -> None:
        rec = self._by_manifest.pop(manifest_ref.hex())
        rec.return_s = time.perf_counter() - self.t0
        rec.busy_s = float(manifest.busy_s)
        rec.bytes_in, rec.bytes_out = int(manifest.bytes_in), int(manifest.bytes_out)
        self._counts[rec.call] = {t: list(c) for t, c in manifest.counts.items()}
        rays = [0] * self.k
        for c in manifest.counts.values():
            rays = [a + int(b) for a, b in zip(rays, c, strict=True)]
        rec.rays_out = rays
        total = sum(r for _, r in rec.inputs)
        shares = [rec.bytes_in * r // total if total else 0 for _, r in rec.inputs]
        if shares:  # integer split; the remainder goes to the first, so they add up exactly
            shares[0] += rec.bytes_in - sum(shares)
        rec.input_bytes = shares

    def to_dict(self) -> dict:
        return {"k": self.k, "calls": [asdict(c) for c in self.calls]}
