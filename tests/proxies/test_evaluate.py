"""Held-out scoring: the confidence curve proxy mode's band implies; runs without torch."""

from __future__ import annotations

import numpy as np

from nprt.proxies.config import ProxyConfig
from nprt.proxies.evaluate import confidence_curve, query_metrics
from nprt.proxies.sampling import sample_rays
from tests.proxies.helpers import sphere, stand_in_proxy


def test_confidence_curve_starts_at_the_held_out_accuracy_and_drops_unsure_queries():
    mesh = sphere()
    proxy = stand_in_proxy(mesh, ProxyConfig(width=16))
    rays = sample_rays(mesh, 4096, seed=3, grid=8)
    vis, _ = proxy.query(rays.points, rays.directions)
    thr = float(np.median(vis))  # half the queries on each side: a real mix of answers
    curve = confidence_curve(proxy, rays, thr, np.array([0.0, 0.01, 0.03, 10.0]))
    assert [c["band"] for c in curve] == [0.0, 0.01, 0.03, 10.0]
    assert curve[0]["share"] == 1.0
    assert curve[0]["accuracy"] == query_metrics(proxy, rays, thr)["accuracy"]
    shares = [c["share"] for c in curve]
    assert shares == sorted(shares, reverse=True) and 0.0 < shares[2] < shares[1] < 1.0
    kept = np.abs(vis - thr) >= 0.03  # what the renderer answers without settling
    assert curve[2]["share"] == kept.mean()
    assert curve[2]["accuracy"] == ((vis >= thr) == rays.hit)[kept].mean()
    assert curve[3] == {"band": 10.0, "share": 0.0, "accuracy": None}
