"""bench/network/netmodel.py on hand-made step traces whose times can be worked out on paper."""

from __future__ import annotations

import pytest

from bench.network.netmodel import cpu_corrected, replay, step_cpu

RPC = 0.01
GBIT = 1e9


def step(shard, n, busy, passes, orders=(), inputs=(), outputs=()):
    return {"shard": shard, "step": n, "busy_s": busy, "passes": list(passes),
            "orders": list(orders), "inputs": list(inputs), "outputs": list(outputs)}


def test_independent_steps_run_in_parallel():
    trace = {"k": 2, "admitted": [0, 1],
             "steps": [step(0, 0, 1.0, [0], orders=[0]), step(1, 0, 2.0, [1], orders=[1])]}
    r = replay(trace, GBIT, RPC, window=4)
    # order (rpc), the longer step, weight back and collect (2 rpc), film back (rpc)
    assert r.makespan_s == pytest.approx(2.0 + 4 * RPC, abs=1e-6)
    assert r.busy_s.tolist() == [1.0, 2.0]


@pytest.mark.parametrize("nbytes", [0, 1_250_000, 12_500_000])
def test_a_parcel_goes_shard_to_shard_at_the_links_bandwidth(nbytes):
    trace = {"k": 2, "admitted": [0], "steps": [
        step(0, 0, 1.0, [0], orders=[0], outputs=[(1, 10, nbytes)]),
        step(1, 0, 1.0, [0], inputs=[(0, 0, 10, nbytes)])]}
    r = replay(trace, GBIT, RPC, window=4)
    wire = nbytes * 8 / GBIT
    assert r.makespan_s == pytest.approx(2.0 + 4 * RPC + wire, abs=1e-6)
    assert r.bytes_moved == nbytes
    # no coordinator hop: the consumer starts as soon as the parcel is in
    assert r.step_start_s[1] == pytest.approx(1.0 + RPC + wire, abs=1e-6)


def test_a_parcel_sent_before_its_step_ends_leaves_at_its_recorded_fraction():
    """remote.EMIT_RAYS: a parcel recorded 0.25 s into a 1 s step leaves a quarter into
    the step as modelled, scaled with the step's compute time; None leaves at the end."""
    trace = {"k": 2, "admitted": [0], "steps": [
        step(0, 0, 1.0, [0], orders=[0], outputs=[(1, 10, 0, 0.25), (1, 10, 0, None)]),
        step(1, 0, 0.5, [0], inputs=[(0, 0, 10, 0, 0.25)]),
        step(1, 1, 0.5, [0], inputs=[(0, 0, 10, 0, None)])]}
    r = replay(trace, GBIT, RPC, window=4)
    assert r.step_start_s[1] == pytest.approx(RPC + 0.25, abs=1e-6)
    assert r.step_start_s[2] == pytest.approx(RPC + 1.0, abs=1e-6)
    slow = replay(trace, GBIT, RPC, window=4, cpu_s=[2.0, 0.5, 0.5])
    assert slow.step_start_s[1] == pytest.approx(RPC + 0.5, abs=1e-6)


def test_two_senders_share_one_receivers_downlink():
    nbytes = 12_500_000  # 0.1 s alone at 1 Gbit/s
    trace = {"k": 3, "admitted": [0, 1], "steps": [
        step(0, 0, 1.0, [0], orders=[0], outputs=[(2, 5, nbytes)]),
        step(1, 0, 1.0, [1], orders=[1], outputs=[(2, 5, nbytes)]),
        step(2, 0, 1.0, [0, 1], inputs=[(0, 0, 5, nbytes), (1, 0, 5, nbytes)])]}
    r = replay(trace, GBIT, RPC, window=4)
    assert r.step_start_s[2] == pytest.approx(1.0 + RPC + 0.2, abs=1e-6)


def test_a_pass_beyond_the_window_waits_for_one_to_finish():
    trace = {"k": 1, "admitted": [0, 1],
             "steps": [step(0, 0, 1.0, [0], orders=[0]), step(0, 1, 1.0, [1], orders=[1])]}
    wide = replay(trace, GBIT, RPC, window=2)
    narrow = replay(trace, GBIT, RPC, window=1)
    # both ordered at once (the second waits for the shard only) ...
    assert wide.step_start_s[1] == pytest.approx(1.0 + RPC, abs=1e-6)
    # ... or the second pass is admitted only when the first's film is back
    assert narrow.step_start_s[1] == pytest.approx(1.0 + 5 * RPC, abs=1e-6)


def test_cpu_correction_scales_each_shards_steps():
    trace = {"k": 2, "admitted": [0],
             "steps": [step(0, 0, 2.0, [0]), step(1, 0, 2.0, [0])]}
    assert cpu_corrected(trace, [0.5, 1.5]).tolist() == [1.0, 2.0]  # never above busy


def test_dedicated_step_time_is_the_smaller_of_cpu_and_busy():
    trace = {"k": 1, "admitted": [0], "steps": [
        {**step(0, 0, 2.0, [0]), "cpu_s": 0.5},  # waited 1.5 s for a core
        {**step(0, 1, 1.0, [0]), "cpu_s": 1.8}]}  # two threads at once
    assert step_cpu(trace).tolist() == [0.5, 1.0]
