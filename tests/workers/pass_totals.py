"""A pass's film and statistics summed over in-process shards (`Shard.collect`), for tests
that compare two ways of running the same passes."""

from __future__ import annotations

from nprt.workers.filmsum import FilmSums


def pass_totals(shards, p) -> tuple[bytes, dict]:
    """(film sums' bytes, {(part, name) or ("hops", h): value summed over shards}) of pass
    p, collected from every shard."""
    total, summed = FilmSums.zeros(p.n_pixels), {}
    for sh in shards:
        for _, sums, st in sh.collect([p.index]):
            if sums is not None:
                total += sums
            for part in ("rays", "transfers", "bytes", "counters"):
                for name, v in (st or {}).get(part, {}).items():
                    summed[(part, name)] = summed.get((part, name), 0) + v
            for h, v in enumerate((st or {}).get("hops_histogram", [])):
                summed[("hops", h)] = summed.get(("hops", h), 0) + v
    return total.to_float().tobytes(), summed
