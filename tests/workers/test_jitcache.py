"""The cold-compile notice names only kernel modules that numba compiles on their own: a
module of inlined helpers never writes a cache index, and would be announced before every
render (it was: "compiling the numba kernels ... (pairs)" on every run of a warm machine)."""

from __future__ import annotations

from nprt.workers.jitcache import KERNELS, _compiles_alone, cold_kernel_modules, note_cold_compile


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
