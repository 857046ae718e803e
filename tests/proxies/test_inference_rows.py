"""A row's net answer does not depend on the batch it is asked in (`Proxy.run`): a shard
merges whatever rays have arrived into one call, so on Ray the batches depend on timing,
and `predict_together` asks several ray kinds in one call."""

from __future__ import annotations

import numpy as np
import pytest

from nprt.proxies.cache import SHIPPED_DIR
from nprt.proxies.inference import NETS, Proxy


def _shipped_by_width() -> list[Proxy]:
    """One shipped proxy of each net width (trained nets: a constant net hides nothing)."""
    seen = {}
    for path in sorted(SHIPPED_DIR.glob("*.nprx")):
        p = Proxy.from_bytes(path.read_bytes())
        seen.setdefault(p.meta["width"], p)
    return list(seen.values())


@pytest.mark.parametrize("proxy", _shipped_by_width(), ids=lambda p: f"width{p.meta['width']}")
def test_a_rows_answer_is_the_same_in_any_batch(proxy):
    rng = np.random.default_rng(0)
    width = proxy.session(NETS[0]).get_inputs()[0].shape[1]
    x = rng.standard_normal((301, width)).astype(np.float32)
    for net in NETS:
        whole = proxy.run(net, x)
        assert whole.shape == (301,) and whole.dtype == np.float32
        alone = np.concatenate([proxy.run(net, x[i:i + 1]) for i in range(len(x))])
        assert alone.tobytes() == whole.tobytes(), net
        for _ in range(60):
            a, n = int(rng.integers(0, 300)), int(rng.integers(1, 40))
            got = proxy.run(net, np.ascontiguousarray(x[a:a + n]))
            assert got.tobytes() == whole[a:a + n].tobytes(), (net, a, n)


def test_calls_counts_one_call_per_chunk_of_rows():
    proxy = _shipped_by_width()[0]
    chunk = proxy.chunk_rows
    assert chunk % 2 == 0  # only a batch's last call may need padding
    assert [proxy.calls(n) for n in (0, 1, chunk, chunk + 1, 3 * chunk)] == [0, 1, 1, 2, 3]
