"""Accuracy and speed of a proxy on held-out rays, measured through onnxruntime (no torch)."""

from __future__ import annotations

import time

import numpy as np

from nprt.proxies.inference import Proxy
from nprt.proxies.sampling import RaySamples, sample_internal_rays, sample_rays
from nprt.scene.model import Mesh

BENCH_BATCH = 1 << 16
BENCH_THREADS = 2


def query_metrics(proxy: Proxy, samples: RaySamples, threshold: float) -> dict:
    """Visibility accuracy, false-positive / false-negative rates and depth error.

    fp_rate = predicted hits among true misses; fn_rate = predicted misses among true hits;
    depth_err_rel = mean |t - t_true| / diag over true hits (depth_err_rel_tp: over true hits
    also predicted as hits, which are the ones whose t the renderer uses)
    """
    vis, t = proxy.query(samples.points, samples.directions)
    pred, hit = vis >= threshold, samples.hit
    err = np.abs(t - samples.t)[hit] / proxy.diag
    tp = pred[hit]
    return {
        "accuracy": float((pred == hit).mean()),
        "fp_rate": float((pred & ~hit).sum() / max(1, (~hit).sum())),
        "fn_rate": float((~pred & hit).sum() / max(1, hit.sum())),
        "hit_fraction": float(hit.mean()),
        "depth_err_rel": float(err.mean()) if err.size else 0.0,
        "depth_err_rel_tp": float(err[tp].mean()) if tp.any() else 0.0,
        "depth_err_rel_p90": float(np.quantile(err, 0.9)) if err.size else 0.0,
    }


def confidence_curve(proxy: Proxy, samples: RaySamples, threshold: float,
                     bands: np.ndarray) -> list[dict]:
    """Accuracy where the renderer trusts the proxy, band by band.

    Proxy mode answers a query itself only when |visibility - threshold| >= band and
    settles the others exactly (nprt.workers.routing.proxy_query), so what decides the image is
    the accuracy on that share, not on every query.
    bands : (b,) float; returns one dict per band: band, share (of queries answered),
    accuracy (on those; None where the share is 0)
    """
    vis, _ = proxy.query(samples.points, samples.directions, min_visibility=np.inf)
    correct = (vis >= threshold) == samples.hit
    margin = np.abs(vis - threshold)
    out = []
    for band in np.asarray(bands, np.float64):
        conf = margin >= band
        out.append({"band": float(band), "share": float(conf.mean()),
                    "accuracy": float(correct[conf].mean()) if conf.any() else None})
    return out


# Bands at which a proxy's held-out error curve is recorded (its report's "curve"): the
# accuracy target picks, per mesh and ray kind, the narrowest of these that meets it.
CURVE_BANDS = (0.0, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)


def error_curve(proxy: Proxy, samples: RaySamples, threshold: float,
                bands=CURVE_BANDS) -> dict:
    """What trusting the proxy outside each band costs, as rates over all held-out queries:
    share (answered by the proxy: |visibility - threshold| >= band), fp (answered "hit"
    where the ray passes: a shadow ray darkened), fn (answered "miss" where it hits: a
    surface skipped by a secondary ray, a shadow ray lit). Lists of floats, one per band."""
    vis, _ = proxy.query(samples.points, samples.directions, min_visibility=np.inf)
    pred, hit = vis >= threshold, samples.hit
    margin = np.abs(vis - threshold)
    out = {"band": [], "share": [], "fp": [], "fn": []}
    for band in bands:
        conf = margin >= band
        out["band"].append(float(band))
        out["share"].append(round(float(conf.mean()), 6))
        out["fp"].append(round(float((conf & pred & ~hit).mean()), 6))
        out["fn"].append(round(float((conf & ~pred & hit).mean()), 6))
    return out


def internal_metrics(proxy: Proxy, mesh: Mesh, n: int, seed: int, threshold: float,
                     geometry=None) -> dict:
    """The paper's internal-ray rule (exit point, reversed direction; a hit iff visible and
    t_proxy <= t_bbox) scored as occlusion against Embree from the true origin.

    internal_far_rate: among occluded rays predicted occluded, the share whose predicted hit
    lies more than 1 % of the diagonal beyond the true first hit. The reversed query finds
    the surface nearest the box exit, so with several layers it names a later one: where
    another box holds a hit in between, such a ray is routed to the wrong shard.
    """
    rays = sample_internal_rays(mesh, n, seed, geometry)
    vis, t = proxy.query(rays.query.points, rays.query.directions)
    pred = (vis >= threshold) & (t <= rays.t_bbox)
    occ = rays.occluded
    both = pred & occ
    far = (rays.t_bbox - t)[both] - rays.t_first[both] > 0.01 * proxy.diag
    return {
        "internal_occlusion_accuracy": float((pred == occ).mean()),
        "internal_fp_rate": float((pred & ~occ).sum() / max(1, (~occ).sum())),
        "internal_fn_rate": float((~pred & occ).sum() / max(1, occ.sum())),
        "internal_far_rate": float(far.mean()) if far.size else 0.0,
    }


def throughput(proxy: Proxy, n: int = BENCH_BATCH, threads: int = BENCH_THREADS,
               repeats: int = 5) -> float:
    """Queries per second of Proxy.query (encoding + both nets) on a batch of n rays."""
    fresh = Proxy.from_bytes(proxy.to_bytes(), threads=threads)
    rng = np.random.default_rng(0)
    lo, hi = fresh.box
    p = (lo + rng.random((n, 3)) * (hi - lo)).astype(np.float32)
    p[:, 0] = lo[0]  # on the min-x face
    d = rng.normal(size=(n, 3)).astype(np.float32)
    d[:, 0] = np.abs(d[:, 0])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    fresh.query(p, d)  # warm-up: session creation, allocator
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fresh.query(p, d)
        best = min(best, time.perf_counter() - t0)
    return n / best


def evaluate(proxy: Proxy, mesh: Mesh, n: int, seed: int, grid: int = 128,
             geometry=None, threshold: float | None = None, speed: bool = True) -> dict:
    """Held-out report: query metrics, the error curve, internal-ray metrics, size and
    queries/s."""
    thr = proxy.meta["threshold"] if threshold is None else threshold
    samples = sample_rays(mesh, n, seed, grid, geometry)
    report = query_metrics(proxy, samples, thr)
    report["curve"] = error_curve(proxy, samples, thr)
    report.update(internal_metrics(proxy, mesh, max(1, n // 4), seed + 1, thr, geometry))
    report["eval_rays"] = int(n)
    report["threshold"] = float(thr)
    report["onnx_bytes"] = int(sum(len(b) for b in proxy.models.values()))
    if speed:
        report["queries_per_s"] = float(throughput(proxy))
    return report
