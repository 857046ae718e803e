"""A step's film: `_Step.splat` adds each contribution to its pass's film as it comes (one
pass over a batch, each row to its pass's slot in the shard's FilmPool), and a pass carried
over several steps keeps what earlier steps added. Whatever the grouping into batches and
steps, each pass's sums are those of its contributions added at once (`accumulate`), with
the ones the words cannot hold summed in a canonical order."""

from __future__ import annotations

import numpy as np
import pytest

from nprt.workers.filmsum import MAX_EXP, FilmSums
from nprt.workers.kernels.filmsum import accumulate
from nprt.workers.passes import count_tiles, pass_at
from nprt.workers.settings import RenderSettings
from nprt.workers.wavefront.filmpool import FilmPool
from nprt.workers.wavefront.shard import _PassState, _Step

SETTINGS = RenderSettings(width=100, height=70, spp=4, tile_size=32, spp_per_pass=4, shards=0)


def _step(states: list[_PassState], films: FilmPool) -> _Step:
    lookup = np.full(count_tiles(SETTINGS), -1, np.int64)
    for j, st in enumerate(states):
        lookup[st.pass_.index % len(lookup)] = j
    return _Step(SETTINGS, states, lookup, films)


def _contributions(rng, passes, m):
    """m contributions on the pixels of `passes`: pixel (m,) uint32, rgb (m, 3) float64
    with zeros, fireflies, values beyond the words and non-finite ones."""
    pixels = np.concatenate([p.pixels(SETTINGS.width) for p in passes])
    pixel = rng.choice(pixels, m).astype(np.uint32)
    rgb = rng.random((m, 3)) ** 4 * 10.0 ** rng.uniform(-4, 5, (m, 1))
    rgb[rng.random(m) < 0.2] = 0.0
    odd = rng.random(m) < 0.01
    rgb[odd, rng.integers(0, 3)] = rng.choice([np.inf, -np.inf, np.nan, 2.0 ** MAX_EXP * 3],
                                                int(odd.sum()))
    return pixel, rgb


def _expected(p, pixel, rgb) -> FilmSums:
    """The pass's film from all its contributions at once."""
    mine = np.flatnonzero(np.isin(pixel, p.pixels(SETTINGS.width)))
    idx = p.local_index(pixel[mine], SETTINGS.width)
    out = FilmSums.zeros(p.n_pixels)
    outside = np.zeros(len(mine), bool)
    if accumulate(idx, rgb[mine], out.words, outside):
        rows = np.flatnonzero(outside)
        i, v = idx[rows], rgb[mine][rows]
        v = np.where(np.abs(v) < 2.0 ** MAX_EXP, 0.0, v)
        order = np.lexsort((v[:, 2], v[:, 1], v[:, 0], i))
        out.rest = np.stack([np.bincount(i[order], weights=v[order, c], minlength=p.n_pixels)
                             for c in range(3)], axis=1)
    return out


def _same(a: FilmSums, b: FilmSums) -> None:
    assert np.array_equal(a.words, b.words)
    assert (a.rest is None) == (b.rest is None)
    if a.rest is not None:
        assert a.rest.tobytes() == b.rest.tobytes()


@pytest.mark.parametrize("seed", range(3))
def test_step_film_equals_the_sums_of_all_contributions_at_once(seed):
    rng = np.random.default_rng(seed)
    passes = [pass_at(SETTINGS, i) for i in (0, 2, 3, 7)]  # distinct tiles, edge ones too
    pixel, rgb = _contributions(rng, passes, 20_000)
    films = FilmPool(SETTINGS.tile_size ** 2)
    # Slots taken between steps make the pool grow (4 slots, then 8) under passes in flight.
    states = {passes[0].index: _PassState(passes[0], films.take(passes[0]))}
    rest = np.arange(len(pixel))
    while len(rest):  # steps over random subsets of the passes, batches of random sizes
        for p in passes[len(states):len(states) + 1]:
            states[p.index] = _PassState(p, films.take(p))
        live = [st for st in states.values() if rng.random() < 0.7] or list(states.values())
        for _ in range(2):  # slots of no pass: taken, the pool grows, released unwritten
            spare = films.take(passes[0])
        films.release(spare, passes[0].n_pixels)
        step = _step(live, films)
        mine = rest[np.isin(pixel[rest], np.concatenate(
            [st.pass_.pixels(SETTINGS.width) for st in live]))]
        mine = rng.permutation(mine)[: max(1, len(mine) // 2)]
        for part in np.array_split(mine, rng.integers(1, 5)):
            as_f32 = rng.random() < 0.5 and np.all(np.abs(rgb[part]) < 1e30)
            step.splat(pixel[part], rgb[part].astype(np.float32) if as_f32 else rgb[part])
            if as_f32:  # the film adds float32 contributions as their float64 values
                rgb[part] = rgb[part].astype(np.float32)
        rest = np.setdiff1d(rest, mine)
    assert len(films.words) > 4  # it grew with passes in flight
    for p in passes:
        _same(states[p.index].sums(films), _expected(p, pixel, rgb))


def test_a_pass_no_step_touched_has_a_zero_film():
    p = pass_at(SETTINGS, 5)
    films = FilmPool(SETTINGS.tile_size ** 2)
    sums = _PassState(p, films.take(p)).sums(films)
    assert sums.words.shape == (p.n_pixels, 3, 2) and not sums.words.any() and sums.rest is None


def test_a_released_slot_comes_back_zeroed_to_the_next_pass():
    films = FilmPool(SETTINGS.tile_size ** 2)
    a, b = pass_at(SETTINGS, 0), pass_at(SETTINGS, 3)
    st = _PassState(a, films.take(a))
    step = _step([st], films)
    step.splat(a.pixels(SETTINGS.width).astype(np.uint32), np.ones((a.n_pixels, 3)))
    assert st.sums(films).words.any()
    again = _PassState(b, films.take(b))
    assert again.slot == st.slot and not again.sums(films).words.any()


def test_a_pass_larger_than_the_slots_is_refused():
    with pytest.raises(ValueError, match="pixels in a pool"):
        FilmPool(16).take(pass_at(SETTINGS, 0))


def test_a_slot_from_before_a_clear_is_refused_and_the_new_holder_keeps_its_film():
    """A collect that raced a reset (a new run) must not free a slot a new pass holds."""
    films = FilmPool(SETTINGS.tile_size ** 2)
    a, b = pass_at(SETTINGS, 0), pass_at(SETTINGS, 3)
    old = _PassState(a, films.take(a))
    films.clear()
    new = _PassState(b, films.take(b))
    assert new.slot[0] == old.slot[0]
    _step([new], films).splat(b.pixels(SETTINGS.width).astype(np.uint32),
                              np.ones((b.n_pixels, 3)))
    with pytest.raises(ValueError, match="film slot"):
        old.sums(films)
    assert new.sums(films).words.any()
