"""The cold-compile notice names only kernel modules that numba compiles on their own: a
module of inlined helpers never writes a cache index, and would be announced before every
render (it was: "compiling the numba kernels ... (pairs)" on every run of a warm machine)."""

from __future__ import annotations

from nprt.workers.jitcache import (
    KERNELS,
    _compiles_alone,
    cold_kernel_modules,
    cold_modules_run_by,
    note_cold_compile,
)


def test_a_module_of_inlined_helpers_never_counts_as_a_compile():
    assert not _compiles_alone('@njit(inline="always", **JIT)\ndef f(x):\n    return x\n')
    assert not _compiles_alone((KERNELS / "pairs.py").read_text())


def test_a_module_with_a_kernel_of_its_own_does():
    assert _compiles_alone("@njit\ndef f(x):\n    return x\n")
    assert _compiles_alone('@njit(inline="always")\ndef g(x):\n    return x\n\n\n'
                           "@njit(**JIT)\ndef f(x):\n    return g(x)\n")
    assert _compiles_alone((KERNELS / "bvh.py").read_text())


def test_a_render_is_told_of_the_cold_kernels_it_runs_and_only_those(tmp_path, monkeypatch,
                                                                      caplog):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))  # an empty cache: all are cold
    assert {"proxy_pairs", "shade", "nearest"} <= set(cold_kernel_modules())
    named = {}
    for where, distributed, proxies in (("reference", False, False), ("exact", True, False),
                                        ("proxy", True, True)):
        caplog.clear()
        assert note_cold_compile(where, distributed, proxies)
        named[where] = caplog.text
    assert "nearest" not in named["reference"] and "proxy_pairs" not in named["reference"]
    assert "nearest" in named["exact"] and "proxy_pairs" not in named["exact"]
    assert "proxy_pairs" in named["proxy"] and "shade" in named["proxy"]


def test_on_a_cold_cache_one_shard_a_node_warms_first():
    from nprt.workers.runtime.pool import first_cold_per_node

    info = [{"node": "a", "cold_kernels": 0}, {"node": "a", "cold_kernels": 3},
            {"node": "b", "cold_kernels": 3}, {"node": "a", "cold_kernels": 3},
            {"node": "b", "cold_kernels": 3}, {"node": "c", "cold_kernels": 0}]
    assert first_cold_per_node(info) == [1, 2]  # node c is warm: its shards wait for none
    assert first_cold_per_node([{**i, "cold_kernels": 0} for i in info]) == []


def test_a_shard_counts_only_the_cold_modules_its_mode_runs(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    exact, proxy = cold_modules_run_by(True), cold_modules_run_by(True, proxies=True)
    assert "proxy_pairs" in proxy and "proxy_pairs" not in exact
    assert set(exact) < set(proxy) <= set(cold_kernel_modules())
