"""Keep the accuracy promise: the image error a proxy render's plan predicts, and a check
after it that renders scattered 8x8 blocks exactly at the same seed (the RNG is counter-based,
so the proxy render's own pixels there are the other side) and measures their PSNR, with a
bootstrap interval over blocks. Driver-side: no kernel, Embree or ONNX Runtime import."""

from __future__ import annotations

import logging
import math

import numpy as np

from nprt.proxies import accuracy as acc
from nprt.workers.film import tonemap_srgb
from nprt.workers.passes import Pass, pass_at

log = logging.getLogger(__name__)

BLOCK = 8  # block edge, pixels (the smallest tile a render takes)
SHARE = 1 / 64  # of the image's blocks, checked
MIN_BLOCKS = 32  # fewer blocks leave the interval too wide to fail a target (heavy tails)
BOOTSTRAP = 2000
CONFIDENCE = 0.95


def check_blocks(width: int, height: int, seed: int, share: float = SHARE,
                 min_blocks: int = MIN_BLOCKS) -> np.ndarray:
    """(b, 2) int64 top-left corners (x0, y0) of the checked blocks: `share` of the image's
    whole 8x8 blocks and at least min_blocks (all where there are fewer), one seeded random
    block in each of b equal runs of the blocks in raster order (stratified: errors cluster
    in space, and an even spread lowers the estimate's variance)."""
    bx, by = width // BLOCK, height // BLOCK
    if bx * by == 0:
        raise ValueError(f"a {width}x{height} image holds no {BLOCK}x{BLOCK} block to check")
    n = min(bx * by, max(min_blocks, math.ceil(share * bx * by)))
    edges = np.linspace(0, bx * by, n + 1)
    start, stop = np.ceil(edges[:-1]).astype(np.int64), np.ceil(edges[1:]).astype(np.int64)
    u = np.random.default_rng([seed, 64]).random(n)
    pick = start + np.minimum((u * (stop - start)).astype(np.int64), stop - start - 1)
    return np.column_stack([pick % bx * BLOCK, pick // bx * BLOCK]).astype(np.int64)


def block_passes(settings, corners: np.ndarray) -> list[Pass]:
    """The render's own passes of the blocks: with tile_size = BLOCK and every sample in one
    pass, pass index = tile index, and each block is one tile."""
    tiles_x = -(-settings.width // BLOCK)
    return [pass_at(settings, int(y) // BLOCK * tiles_x + int(x) // BLOCK) for x, y in corners]


def render_blocks(scene, settings, corners: np.ndarray, ray_address=None, proxy_dir=None,
                  pools=None) -> tuple[np.ndarray, float]:
    """Render the blocks exactly at the job's K, seed and samples: proxy mode with accuracy
    'exact' settles every proxy answer by exact forwarding (the image is exact mode's), on
    the job's placement, so a warm pool of the job (from `pools`, a PoolRegistry) is reused;
    else a pool of its own starts. Returns (b, 8, 8, 3) float64 linear radiance and the wall
    seconds it took (the check's cost: 1/64 of an exact render, plus a pool start)."""
    import time

    from nprt.workers.render import make_renderer

    t0 = time.perf_counter()
    knobs = settings.proxy.model_copy(update={"accuracy": acc.EXACT, "check": False})
    exact = settings.model_copy(update={"tile_size": BLOCK, "spp_per_pass": settings.spp,
                                        "proxy": knobs})
    out = np.zeros((len(corners), BLOCK * BLOCK, 3))
    passes = block_passes(exact, corners)
    slot = {p.index: i for i, p in enumerate(passes)}
    renderer = make_renderer(scene, exact, ray_address, proxy_dir, pools)
    try:
        finished = renderer.render_passes(iter(passes), None)
        try:
            for p, sums, _ in finished:
                out[slot[p.index]] = sums / (p.sample1 - p.sample0)
        finally:
            finished.close()
    finally:
        renderer.close()
    return out.reshape(len(corners), BLOCK, BLOCK, 3), time.perf_counter() - t0


def film_blocks(film, corners: np.ndarray) -> np.ndarray:
    """(b, 8, 8, 3) float64 linear radiance of a finished film at the blocks."""
    img = film.image().astype(np.float64)
    return np.stack([img[y:y + BLOCK, x:x + BLOCK] for x, y in corners])


def block_psnr(reference: np.ndarray, test: np.ndarray, seed: int = 0) -> dict:
    """PSNR on sRGB (as nprt.workers.stats.quality.compare) over all blocks, and its
    CONFIDENCE interval from a bootstrap over blocks (errors cluster in space, so the block,
    not the pixel, is the independent unit). reference, test : (b, 8, 8, 3) linear."""
    a = tonemap_srgb(reference).astype(np.float64) / 255.0
    b = tonemap_srgb(test).astype(np.float64) / 255.0
    mse = ((a - b) ** 2).reshape(len(a), -1).mean(axis=1)  # (b,) per block
    boot = np.random.default_rng(seed).integers(0, len(mse), (BOOTSTRAP, len(mse)))
    means = np.sort(mse[boot].mean(axis=1))
    tail = (1 - CONFIDENCE) / 2
    lo_mse, hi_mse = means[int(tail * BOOTSTRAP)], means[int((1 - tail) * BOOTSTRAP) - 1]
    return {"psnr_db": _db(mse.mean()), "interval_db": [_db(hi_mse), _db(lo_mse)],
            "blocks": int(len(mse)), "pixels": int(mse.size * BLOCK * BLOCK)}


def _db(mse: float) -> float | None:
    """PSNR of an MSE on [0, 1] images; None (JSON-safe infinity) where they are equal."""
    return round(-10.0 * math.log10(mse), 2) if mse > 0 else None


def prediction(plan, proxies_settings, counters: dict, rays: dict, area: dict) -> dict:
    """Predicted PSNR before the render (prior query shares from box areas) and with the
    shares this render measured. plan: a ProxyPlan; area: mesh -> instance box area."""
    bands = acc.job_bands(plan.proxies, proxies_settings)
    before = acc.predict_error(plan.proxies, bands, acc.prior_queries(plan.proxies, area))
    after = acc.predict_error(plan.proxies, bands, acc.measured_queries(counters, rays))
    return {"before": before.to_dict(), "measured_shares": after.to_dict(),
            "bands": {str(m): {"secondary": b[0], "shadow": b[1]} for m, b in bands.items()},
            "uncalibrated": sorted(int(m) for m, p in plan.proxies.items()
                                   if acc.curve_of(p) is None)}


def verdict(target, predicted_db, measured: dict | None) -> dict:
    """target: dB, 'exact' or None. met: the check's upper bound reaches the target (None
    without a check); warning: a sentence to show loudly where it does not."""
    out = {"target_db": target, "predicted_db": predicted_db, "check": measured,
           "met": None, "warning": None}
    if measured is None or target is None:
        return out
    goal = math.inf if target == acc.EXACT else float(target)
    hi = measured["interval_db"][1]
    hi = math.inf if hi is None else hi
    out["met"] = bool(hi >= goal)
    if not out["met"]:
        shown = "exact" if target == acc.EXACT else f"{goal:g} dB"
        out["warning"] = (f"ACCURACY TARGET MISSED: the exact check of {measured['blocks']} "
                          f"blocks measured {measured['psnr_db']} dB (95 % interval "
                          f"{measured['interval_db'][0]} to {measured['interval_db'][1]}), "
                          f"below the {shown} asked for")
        log.warning("%s", out["warning"])
    return out


def instance_box_areas(scene) -> dict[int, float]:
    """mesh -> summed surface area of its instances' world boxes (a Scene or SceneMeta)."""
    bounds = np.stack([np.asarray(m.bounds, np.float64) for m in scene.meshes])  # (meshes, 2, 3)
    mesh = np.asarray(scene.instance_mesh, np.int64)
    xf = np.asarray(scene.instance_transform, np.float64)  # (m, 4, 4)
    sign = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], bool)  # (8, 3)
    corners = np.where(sign[None], bounds[mesh, 1][:, None], bounds[mesh, 0][:, None])
    world = np.einsum("mij,mkj->mki", xf[:, :3, :3], corners) + xf[:, None, :3, 3]  # (m, 8, 3)
    e = world.max(axis=1) - world.min(axis=1)
    area = 2.0 * (e[:, 0] * e[:, 1] + e[:, 1] * e[:, 2] + e[:, 0] * e[:, 2])
    total = np.bincount(mesh, weights=area, minlength=len(bounds))
    return {int(m): float(total[m]) for m in np.unique(mesh)}


def accuracy_report(scene, settings, plan, stats) -> dict:
    """What a proxy-mode job reports beside its image: target and prediction (before the
    render, and with the query shares it measured); `run_check` adds the check."""
    pred = prediction(plan, settings.proxy, dict(stats.counters), dict(stats.rays),
                      instance_box_areas(scene))
    out = verdict(settings.proxy.accuracy, pred["measured_shares"]["psnr_db"], None)
    out["prediction"] = pred
    return out


def run_check(scene, settings, film, report: dict, ray_address=None, proxy_dir=None,
              pools=None) -> dict:
    """`report` (accuracy_report's) with the exact check of scattered blocks of `film` and
    whether the target was met (loudly, where it was not)."""
    corners = check_blocks(settings.width, settings.height, settings.seed)
    exact, wall_s = render_blocks(scene, settings, corners, ray_address, proxy_dir, pools)
    measured = block_psnr(exact, film_blocks(film, corners), settings.seed)
    measured["wall_s"] = round(wall_s, 3)
    return {**report, **verdict(settings.proxy.accuracy, report["predicted_db"], measured)}


def summary_lines(report: dict) -> list[str]:
    """The accuracy lines of a job summary: target, prediction, check; the warning last."""
    t = report["target_db"]
    target = "hand-set bands" if t is None else ("exact" if t == acc.EXACT else f"{t:g} dB")
    pred = report["predicted_db"]
    line = f"accuracy: target {target}, predicted {'inf' if pred is None else pred} dB"
    c = report.get("check")
    if isinstance(c, dict):
        lo, hi = c["interval_db"]
        line += (f", checked {c['psnr_db'] if c['psnr_db'] is not None else 'inf'} dB "
                 f"(95 % {lo} to {hi if hi is not None else 'inf'}, {c['blocks']} blocks, "
                 f"{c['wall_s']:.1f} s)")
    elif c == "deferred":
        line += ", check pending"
    out = [line]
    if report.get("warning"):
        out.append(f"WARNING: {report['warning']}")
    return out
