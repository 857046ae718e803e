"""The batch glue of a wavefront step: `gather` (the rows of several batches in one copy),
`group_rows` (rows by target shard in one counting pass), a batch's `nbytes`, the step's
pass tokens taken from a known column's (`_Step.tok` with of / rows) and its statistics
counted in place (`SplitStats`). Each must give exactly what the plain numpy it replaces
gives."""

from __future__ import annotations

import numpy as np
import pytest

from nprt.workers.kernels.buckets import group_rows
from nprt.workers.passes import count_tiles, pass_at
from nprt.workers.settings import RenderSettings
from nprt.workers.stats.counters import MAX_HOPS, RenderStats, SplitStats
from nprt.workers.wavefront.batch import FLAG_SHADE, SHADOW, RayBatch, ShadowRayBatch
from nprt.workers.wavefront.filmpool import FilmPool
from nprt.workers.wavefront.shard import _PassState, _split_settled, _Step


def _random(cls, rng, n: int):
    """A batch of n rows of random bytes in every column (any bit pattern must survive)."""
    cols = {}
    for name, (width, dtype) in cls._SPEC.items():
        shape = (n,) if width is None else (n, width)
        raw = rng.integers(0, 256, int(np.prod(shape)) * np.dtype(dtype).itemsize, np.uint8)
        cols[name] = raw.view(dtype).reshape(shape)
    return cls(**cols)


def _same(a, b) -> None:
    for name in a._SPEC:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), name


@pytest.mark.parametrize("cls", [RayBatch, ShadowRayBatch])
@pytest.mark.parametrize("seed", range(4))
def test_gather_equals_take_then_concat_for_any_parts(cls, seed):
    rng = np.random.default_rng(seed)
    parts = []
    for _ in range(rng.integers(1, 6)):
        b = _random(cls, rng, int(rng.integers(0, 40)))
        how = rng.integers(0, 4)
        if how == 0:
            rows = None
        elif how == 1:
            rows = rng.random(len(b)) < 0.5  # a mask
        elif how == 2:
            rows = rng.integers(0, max(len(b), 1), int(rng.integers(0, 30))) if len(b) else \
                np.zeros(0, np.int64)  # an index array, rows repeated and out of order
        else:
            rows = np.zeros(0, np.int64)
        parts.append((b, rows))
    parts.append((None, None))  # no batch: skipped
    want = cls.concat([b if r is None else b.take(r) for b, r in parts if b is not None])
    _same(cls.gather(parts), want)


def test_gather_of_every_row_of_one_batch_is_that_batch():
    b = _random(RayBatch, np.random.default_rng(0), 9)
    assert RayBatch.gather([(b, None)]) is b
    assert RayBatch.gather([(RayBatch.empty(), None), (b, np.ones(9, bool))]) is b
    assert len(RayBatch.gather([])) == 0


@pytest.mark.parametrize("k", [1, 3, 8])
def test_group_rows_equals_a_stable_sort_by_target(k):
    rng = np.random.default_rng(k)
    target = rng.integers(-1, k, 500).astype(np.int32)
    order, starts = group_rows(target, k)
    assert np.array_equal(order, np.argsort(target, kind="stable"))
    assert np.array_equal(np.diff(starts), np.bincount(target + 1, minlength=k + 1))
    assert starts[0] == 0 and starts[-1] == len(target)


@pytest.mark.parametrize("bad", [-2, 3])
def test_group_rows_refuses_a_target_outside_the_shards(bad):
    with pytest.raises(ValueError, match="outside"):
        group_rows(np.array([0, bad], np.int32), 3)


@pytest.mark.parametrize("cls", [RayBatch, ShadowRayBatch])
def test_nbytes_is_the_sum_of_the_columns_bytes(cls):
    b = _random(cls, np.random.default_rng(1), 13)
    for batch in (b, b.rows(2, 7), b.take(np.array([3, 3, 1])), cls.empty()):
        assert batch.nbytes == sum(getattr(batch, n).nbytes for n in cls._SPEC)


def test_pass_tokens_taken_from_a_known_column_equal_the_lookup():
    s = RenderSettings(width=100, height=70, spp=4, tile_size=32, spp_per_pass=4, shards=0)
    films = FilmPool(s.tile_size ** 2)
    states = [_PassState(pass_at(s, i), films.take(pass_at(s, i))) for i in (0, 4, 5, 11)]
    lookup = np.full(count_tiles(s), -1, np.int64)
    for j, st in enumerate(states):
        lookup[st.pass_.index % len(lookup)] = j
    rng = np.random.default_rng(2)
    pixel = rng.choice(np.concatenate([st.pass_.pixels(s.width) for st in states]),
                       300).astype(np.uint32)
    step, fresh = _Step(s, states, lookup, films), _Step(s, states, lookup, films)
    whole = step.tok(pixel)
    assert np.array_equal(whole, fresh.tok(pixel))
    for rows in (rng.random(300) < 0.3, rng.integers(0, 300, 50)):
        sub = pixel[rows]
        assert np.array_equal(step.tok(sub, pixel, rows), fresh.tok(sub.copy()))
    # Without the known column's answer kept, the lookup is made: still the same tokens.
    other = rng.choice(pixel, 40)
    sub = other[5:20]
    assert np.array_equal(fresh.tok(sub, other, np.arange(5, 20)), step.tok(sub.copy()))


def test_step_counts_equal_a_bincount_over_pass_and_key():
    rng = np.random.default_rng(3)
    t, n = 5, 400
    parts = [RenderStats() for _ in range(t)]
    stats = SplitStats(parts)
    tok = rng.integers(0, t, n)
    kind = rng.integers(0, 3, n).astype(np.uint8)
    hops = rng.integers(0, 255, n).astype(np.uint8)  # beyond MAX_HOPS: counted at MAX_HOPS
    mask = rng.random(n) < 0.4
    index = rng.integers(0, n, 60)
    stats.bind(tok)
    stats.count_rays(kind)
    stats.count_rays(SHADOW)
    stats.count_hops(hops)
    stats.count_hops(hops, mask)
    stats.count_hops(hops, index)
    stats.count_transfers(kind, 7)
    stats.count_transfers(SHADOW, 5)

    def grid(tk, key, width):
        return np.bincount(tk * width + np.minimum(key, width - 1),
                           minlength=t * width).reshape(t, width)

    want_rays = grid(tok, kind, 3) + grid(tok, np.full(n, SHADOW), 3)
    hop_w = MAX_HOPS + 1
    want_hops = grid(tok, hops, hop_w) + grid(tok[mask], hops[mask], hop_w) + \
        grid(tok[index], hops[index], hop_w)
    sent_kind, sent_shadow = grid(tok, kind, 3), grid(tok, np.full(n, SHADOW), 3)
    assert np.array_equal(stats._rays, want_rays)
    assert np.array_equal(stats._hops, want_hops)
    assert np.array_equal(stats._sent, sent_kind + sent_shadow)
    assert np.array_equal(stats._sent_bytes, 7 * sent_kind + 5 * sent_shadow)


def test_a_row_of_no_pass_in_the_step_is_refused_by_the_counts():
    stats = SplitStats([RenderStats(), RenderStats()]).bind(np.array([0, 2, 1]))
    with pytest.raises(ValueError, match="not in this step"):
        stats.count_rays(np.zeros(3, np.uint8))
    with pytest.raises(ValueError, match="not in this step"):
        stats.count_rays(SHADOW)
    with pytest.raises(ValueError, match="expected shape"):
        stats.count_hops(np.zeros(4, np.uint8))


@pytest.mark.parametrize("first", [True, False])
def test_split_settled_gives_the_flagged_rays_then_the_rest_in_order(first):
    """Whether a parcel holds its rays to be shaded first (as `_by_target` packs them) or
    anywhere: the flagged rays of every parcel in order, their flag cleared, and the rest
    followed by the rays made here."""
    rng = np.random.default_rng(5)
    received = []
    for n in (30, 0, 17, 25):
        b = _random(RayBatch, rng, n)
        flagged = rng.random(n) < 0.4
        if first:
            flagged = np.sort(flagged)[::-1]
        flags = (b.flags & np.uint8(~FLAG_SHADE & 0xFF)) | (flagged * FLAG_SHADE).astype(np.uint8)
        received.append(b.replace(flags=flags))
    made = [_random(RayBatch, rng, 9)]
    arrived, rays = _split_settled(received, made)
    whole = RayBatch.concat(received)
    mask = (whole.flags & FLAG_SHADE) != 0
    want = whole.take(mask)
    _same(arrived, want.replace(flags=want.flags & np.uint8(~FLAG_SHADE & 0xFF)))
    _same(rays, RayBatch.concat([whole.take(~mask), *made]))
