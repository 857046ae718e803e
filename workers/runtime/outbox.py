"""Small parcels wait for company before they leave a shard.

A wavefront step makes one parcel per target at its end, and a few more during it when
many rays are leaving (`Shard.step`, `remote.EMIT_RAYS`). Ray charges each parcel a CPU
cost that hardly depends on what it carries: in city exact at K = 8 (320x180, 8 spp, 2
cores) about 0.36 ms in the sending thread and 1.4 ms in the Ray threads of both processes
(bench/render/raycalls.py measures it per run). Yet most parcels are small: in
that render 66 % of them carried fewer than 100 rays (5 % of the rays), 29 % fewer than 10.

So a parcel for a target waits in the `Outbox` while the shard has more work, merged with
that target's parcels of the next steps, and leaves when any of these holds:
- the target's held parcels carry `min_rays` rays together;
- the oldest of them has waited `wait_s` (checked at the end of each step);
- the shard's inbox is empty after a step (`flush`): nothing would come to push them on,
  and a shard that waits idle with rays held would stall the passes they belong to.

The price is latency: a held parcel's rays arrive up to a step later, so a pass whose last
rays wait completes later too (the coordinator's window keeps other passes in flight).

Termination stays exact: a held parcel keeps its credits (pass weight), and a shard holds
parcels only while its inbox is not empty, so it never looks idle with weight held. Films
do not depend on how rays are grouped into parcels or steps, so exact mode still equals
the reference bit for bit (tests/distributed/test_step_hold.py).

Rejected: merging on the receiving side (the receiver already merges its whole inbox into
one step, `remote.HOLD_RAYS`; the cost saved here is the Ray call itself, which only the
sender can avoid), and a minimum size with no age bound (a pass whose last rays trickle
to one target, a few a step, would wait for the shard to run dry)."""

from __future__ import annotations

import time

import numpy as np

from nprt.workers.runtime.protocol import Parcel, sum_credits


class Outbox:
    """The parcels one shard holds back, per target. k: shards; min_rays, wait_s: as the
    module says (min_rays 0: every parcel leaves at once)."""

    def __init__(self, k: int, min_rays: int = 0, wait_s: float = 0.0):
        if min_rays < 0 or wait_s < 0:
            raise ValueError(f"min_rays and wait_s cannot be negative: {min_rays}, {wait_s}")
        self.min_rays, self.wait_s = int(min_rays), float(wait_s)
        self._held: list[list[Parcel]] = [[] for _ in range(k)]
        self._rays = [0] * k  # rays held per target
        self._since = [0.0] * k  # when each target's oldest held parcel was made

    @property
    def held_rays(self) -> int:
        return sum(self._rays)

    def put(self, parcels: list, now: float, flush: bool) -> list[tuple[int, Parcel]]:
        """Hold parcels ((k,) list, Parcel or None per target) of a step that ended at
        `now` (time.monotonic()); returns the (target, parcel) pairs that leave now, one
        merged parcel per target. flush: everything leaves."""
        for t, p in enumerate(parcels):
            if p is None:
                continue
            if not self._held[t]:
                self._since[t] = now
            self._held[t].append(p)
            self._rays[t] += p.n_rays
        leaving = []
        for t, held in enumerate(self._held):
            if held and (flush or self._rays[t] >= self.min_rays
                         or now - self._since[t] >= self.wait_s):
                leaving.append((t, merge(held)))
                self._held[t], self._rays[t] = [], 0
        return leaving


def merge(parcels: list[Parcel]) -> Parcel:
    """One parcel holding the rays, shadow rays, camera rays and credits of `parcels` (made
    by one shard for one target). Rays to be shaded there (FLAG_SHADE) come first, as in
    each parcel (`Shard._by_target`), so the receiver still slices them off."""
    if any(p.orders for p in parcels):  # the coordinator's alone: a merge would drop them
        raise ValueError("a parcel with camera-ray orders cannot be merged")
    if len(parcels) == 1:
        return parcels[0]
    from nprt.workers.wavefront.batch import FLAG_SHADE  # shard-side only: not the driver's

    credits = sum_credits(p.credits for p in parcels)
    rays = [p.rays for p in parcels if p.rays is not None and len(p.rays)]
    merged_rays = None
    if rays:
        settled = [int(np.count_nonzero(b.flags & FLAG_SHADE)) for b in rays]
        parts = [b.rows(0, s) for b, s in zip(rays, settled, strict=True)]
        parts += [b.rows(s, len(b)) for b, s in zip(rays, settled, strict=True)]
        merged_rays = type(rays[0]).concat(parts)
    shadow = [p.shadow for p in parcels if p.shadow is not None and len(p.shadow)]
    merged_shadow = type(shadow[0]).concat(shadow) if shadow else None
    cams = [p.camera for p in parcels if p.camera is not None]
    camera = tuple(np.concatenate(c) for c in zip(*cams, strict=True)) if cams else None
    return Parcel(parcels[0].epoch, credits, merged_rays, merged_shadow, camera=camera,
                  sent_at=time.time())
