"""Tile events: after each pass, the tile's pixels so far go to the store's events table,
from which every API worker streams them to its watchers (nprt.service.feed)."""

from __future__ import annotations

import numpy as np

from nprt.service.store import JobStore
from nprt.workers.render import PassDone


def publish_tile(store: JobStore, job_id: str, p: PassDone, base: int, total: int) -> None:
    """Store pass p's tile. base, total: passes of the frames before this one and of the
    whole job (frames jobs count every frame's passes)."""
    t = p.pass_
    pix = t.pixels(p.film.width)
    with p.film.lock:
        rgb = p.film.sums[pix] / np.maximum(p.film.samples[pix], 1)[:, None]
    tile = {"pass_index": p.index, "passes_total": p.total, "rect": [t.x0, t.y0, t.x1, t.y1],
            "sample0": t.sample0, "sample1": t.sample1,
            "progress": (base + p.progress.count) / total}
    store.tile_event(job_id, tile, rgb.astype(np.float32).tobytes())
