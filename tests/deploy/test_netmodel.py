"""bench/network/netmodel.py on hand-made traces whose times can be worked out on paper."""

from __future__ import annotations

import pytest

from bench.network.netmodel import cpu_corrected, replay

RPC = 0.01
GBIT = 1e9


def call(i, shard, tokens, busy, inputs=(), input_bytes=(), rays_out=None, k=2):
    return {"call": i, "shard": shard, "tokens": list(tokens), "busy_s": busy,
            "inputs": list(inputs), "input_bytes": list(input_bytes),
            "rays_out": rays_out or [0] * k}


def test_independent_calls_run_in_parallel():
    trace = {"k": 2, "calls": [call(0, 0, [0], 1.0), call(1, 1, [0], 2.0)]}
    r = replay(trace, GBIT, RPC, window=4)
    # dispatch (rpc), the longer call, return (rpc), collect out and film back (2 rpc)
    assert r.makespan_s == pytest.approx(2.0 + 4 * RPC, abs=1e-6)
    assert r.busy_s.tolist() == [1.0, 2.0]


@pytest.mark.parametrize("nbytes", [0, 1_250_000, 12_500_000])
def test_a_parcel_crosses_the_link_at_its_bandwidth(nbytes):
    trace = {"k": 2, "calls": [
        call(0, 0, [0], 1.0, rays_out=[0, 10]),
        call(1, 1, [0], 1.0, inputs=[(0, 10)], input_bytes=[nbytes])]}
    r = replay(trace, GBIT, RPC, window=4)
    wire = nbytes * 8 / GBIT
    assert r.makespan_s == pytest.approx(2.0 + 6 * RPC + wire, abs=1e-6)
    assert r.bytes_moved == nbytes
    # the consumer starts once its parcel is in: after dispatch, arrival and the wire
    assert r.call_start_s[1] == pytest.approx(1.0 + 3 * RPC + wire, abs=1e-6)


def test_two_senders_share_one_receivers_downlink():
    nbytes = 12_500_000  # 0.1 s alone at 1 Gbit/s
    trace = {"k": 3, "calls": [
        call(0, 0, [0], 1.0, rays_out=[0, 0, 5], k=3),
        call(1, 1, [0], 1.0, rays_out=[0, 0, 5], k=3),
        call(2, 2, [0], 1.0, inputs=[(0, 5), (1, 5)], input_bytes=[nbytes, nbytes], k=3)]}
    r = replay(trace, GBIT, RPC, window=4)
    assert r.call_start_s[2] == pytest.approx(1.0 + 3 * RPC + 0.2, abs=1e-6)


def test_a_pass_beyond_the_window_waits_for_one_to_finish():
    trace = {"k": 1, "calls": [call(0, 0, [0], 1.0, k=1), call(1, 0, [1], 1.0, k=1)]}
    wide = replay(trace, GBIT, RPC, window=2)
    narrow = replay(trace, GBIT, RPC, window=1)
    # both queued at once (the second waits for the shard only) ...
    assert wide.call_start_s[1] == pytest.approx(1.0 + RPC, abs=1e-6)
    # ... or the second pass is admitted only when the first's film is back
    assert narrow.call_start_s[1] == pytest.approx(1.0 + 4 * RPC + RPC, abs=1e-6)


def test_cpu_correction_scales_each_shards_calls():
    trace = {"k": 2, "calls": [call(0, 0, [0], 2.0), call(1, 1, [0], 2.0)]}
    assert cpu_corrected(trace, [0.5, 1.5]).tolist() == [1.0, 2.0]  # never above busy
