"""A pass's film and statistics summed over in-process shards (`Shard.collect`), and the
delivery of a step's parcels round by round, for tests that compare two ways of running the
same passes."""

from __future__ import annotations

from fractions import Fraction

from nprt.workers.filmsum import FilmSums


def deliver(inbox: dict, parcels: list) -> int:
    """A step's parcels ((k,) Parcel or None) into the next round's inbox, {shard: (orders,
    parcels, credits)}, their weights summed per pass. Returns how many there were."""
    sent = 0
    for t, out in enumerate(parcels):
        if out is None:
            continue
        sent += 1
        _, got, owed = inbox.setdefault(t, ([], [], {}))
        got.append(out)
        for i, w in out.credits.items():
            owed[i] = owed.get(i, Fraction(0)) + w
    return sent


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
