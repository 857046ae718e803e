"""The proxy blob: round trip, corruption detection, query shapes; runs without torch."""

from __future__ import annotations

import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from ray import cloudpickle

from nprt.proxies.config import ProxyConfig
from nprt.proxies.inference import Proxy, ProxyFormatError
from tests.proxies.helpers import sphere, stand_in_proxy

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def proxy():
    return stand_in_proxy(sphere(), ProxyConfig(width=16))


def test_blob_round_trip_keeps_meta_models_and_answers(proxy):
    blob = proxy.to_bytes()
    back = Proxy.from_bytes(blob)
    assert back.to_bytes() == blob and back.nbytes == len(blob)
    assert back.meta == proxy.meta and back.models == proxy.models
    p = np.array([[-1.1, 0.0, 0.0], [0.0, 1.1, 0.2]], np.float32)
    d = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], np.float32)
    for a, b in zip(proxy.query(p, d), back.query(p, d), strict=True):
        np.testing.assert_array_equal(a, b)
    # ray.put uses cloudpickle, which once pickled the class's module by value and failed.
    for dumps in (pickle.dumps, cloudpickle.dumps):
        again = pickle.loads(dumps(back))
        assert len(dumps(back)) < len(blob) + 1024  # the blob, not a module
        np.testing.assert_array_equal(again.query(p, d)[0], back.query(p, d)[0])


@pytest.mark.parametrize("damage", ["flip_payload", "truncate", "bad_magic", "bad_header"])
def test_damaged_blob_is_refused(proxy, damage):
    blob = bytearray(proxy.to_bytes())
    if damage == "flip_payload":
        blob[-10] ^= 0xFF
    elif damage == "truncate":
        blob = blob[:-7]
    elif damage == "bad_magic":
        blob[0] ^= 0xFF
    else:
        blob[14] = ord("}")
    with pytest.raises(ProxyFormatError):
        Proxy.from_bytes(bytes(blob))


def test_query_checks_shapes_and_handles_empty_batches(proxy):
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        proxy.query(np.zeros((4, 2), np.float32), np.zeros((4, 2), np.float32))
    vis, t = proxy.query(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32))
    assert vis.shape == t.shape == (0,)


def test_min_visibility_skips_depth_for_rejected_rows(proxy):
    rng = np.random.default_rng(0)
    lo, hi = proxy.box
    p = (lo + rng.random((1000, 3)) * (hi - lo)).astype(np.float32)
    p[:, 2] = lo[2]
    d = np.tile(np.array([[0, 0, 1]], np.float32), (1000, 1))
    vis, t_all = proxy.query(p, d)
    thr = float(np.median(vis))
    vis2, t = proxy.query(p, d, min_visibility=thr)
    keep = vis >= thr
    np.testing.assert_array_equal(vis, vis2)
    np.testing.assert_allclose(t[keep], t_all[keep])
    assert np.isinf(t[~keep]).all()


def test_points_on_the_mesh_box_give_distances_from_those_points(proxy):
    # The caller's box (mesh AABB) is inside the padded proxy box; the answer is measured
    # from the caller's point, so it is the proxy-box answer minus the slide along the ray.
    lo_m, hi_m = proxy.meta["bounds"]
    p_mesh = np.array([[lo_m[0], 0.1, 0.2]], np.float32)
    d = np.array([[0.8, 0.6, 0.0]], np.float32)
    lo = proxy.box[0]
    s = (p_mesh[0, 0] - lo[0]) / d[0, 0]
    p_box = p_mesh - s * d
    _, t_mesh = proxy.query(p_mesh, d)
    _, t_box = proxy.query(p_box.astype(np.float32), d)
    np.testing.assert_allclose(t_mesh, np.maximum(t_box - s, 0), rtol=1e-4, atol=1e-6)


def test_the_render_path_never_imports_torch():
    code = ("import sys; import nprt.proxies.inference, nprt.proxies.cache, nprt.proxies.policy, "
            "nprt.proxies.evaluate, nprt.proxies.sampling, nprt.proxies.cli; "
            "assert 'torch' not in sys.modules, 'torch imported'")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)
