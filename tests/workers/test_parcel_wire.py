"""A parcel on the wire: each ray batch travels as one buffer (Ray's serializer pays per
array), and comes back with every column the same bits, dtype and shape."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from nprt.workers.runtime.protocol import Parcel
from nprt.workers.wavefront.batch import RayBatch, ShadowRayBatch


def _random(cls, n: int, rng):
    cols = {}
    for name, (width, dtype) in cls._SPEC.items():
        shape = (n,) if width is None else (n, width)
        raw = rng.integers(0, 256, int(np.prod(shape)) * np.dtype(dtype).itemsize, np.uint8)
        cols[name] = raw.view(dtype).reshape(shape)  # any bits, NaNs included
    return cls(**cols)


def _roundtrip(parcel: Parcel) -> tuple[Parcel, list]:
    buffers = []
    blob = pickle.dumps(parcel, protocol=5, buffer_callback=buffers.append)
    return pickle.loads(blob, buffers=buffers), buffers


@pytest.mark.parametrize("n", (0, 1, 7, 1000))
def test_a_parcel_comes_back_bit_for_bit_from_one_buffer_per_batch(n):
    rng = np.random.default_rng(n)
    sent = Parcel(5, {3: 1}, _random(RayBatch, n, rng), _random(ShadowRayBatch, n + 2, rng),
                  source=(1, 9, 0.25))
    got, buffers = _roundtrip(sent)
    assert len(buffers) == 2  # one per batch, not one per column
    for a, b in ((sent.rays, got.rays), (sent.shadow, got.shadow)):
        assert type(b) is type(a) and len(b) == len(a)
        for name in a._SPEC:
            x, y = getattr(a, name), getattr(b, name)
            assert x.dtype == y.dtype and x.shape == y.shape
            assert x.tobytes() == y.tobytes(), name
    assert (got.epoch, got.credits, got.source, got.sent_at) == \
        (sent.epoch, sent.credits, sent.source, sent.sent_at)
    assert got.nbytes == sent.nbytes and got.n_rays == sent.n_rays


def test_an_order_or_camera_parcel_keeps_its_fields():
    cam = (np.arange(4, dtype=np.uint32), np.arange(4, dtype=np.uint32) * 2)
    sent = Parcel(1, {0: 1}, camera=cam)
    got, _ = _roundtrip(sent)
    assert got.rays is None and got.shadow is None
    assert all(np.array_equal(a, b) for a, b in zip(got.camera, cam, strict=True))


def test_columns_received_read_only_reach_the_kernels_as_the_shards_own_rays():
    """Ray hands call arguments over read-only, and numba types a read-only array apart
    (it compiled every walk again inside the first render on Ray). A received parcel's
    columns and camera arrays are writable, of the same numba type as the sender's."""
    numba = pytest.importorskip("numba")
    rng = np.random.default_rng(3)
    cam = (np.arange(4, dtype=np.uint32), np.arange(4, dtype=np.uint32) * 2)
    sent = Parcel(2, {0: 1}, _random(RayBatch, 9, rng), _random(ShadowRayBatch, 4, rng),
                  camera=cam)
    buffers = []
    blob = pickle.dumps(sent, protocol=5, buffer_callback=buffers.append)
    frozen = [pickle.PickleBuffer(bytes(b.raw())) for b in buffers]  # as Ray's: read-only
    assert all(memoryview(b).readonly for b in frozen)
    got = pickle.loads(blob, buffers=frozen)
    pairs = [(getattr(a, name), getattr(b, name)) for a, b in
             ((sent.rays, got.rays), (sent.shadow, got.shadow)) for name in a._SPEC]
    pairs += list(zip(sent.camera, got.camera, strict=True))
    for x, y in pairs:
        assert y.flags.writeable
        assert numba.typeof(y) == numba.typeof(x)
        assert x.tobytes() == y.tobytes()
