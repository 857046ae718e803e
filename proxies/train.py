"""Training both proxy nets on the CPU under a seeded sample and step budget (imports torch).

Deterministic: the same mesh and ProxyConfig give a bit-identical proxy blob on the same
platform, however loaded the machine is. Sampling is seeded, the step count is fixed, torch
runs deterministic kernels on TRAIN_THREADS threads, and wall-clock figures stay out of the
blob (Proxy.timing). SAFETY_CAP_S only stops a runaway run; a proxy that hit it says so
(report["capped"]) and is not reproducible.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time

import numpy as np
import torch
from tqdm.auto import tqdm

from nprt.proxies.config import EVAL_SEED_OFFSET, ProxyConfig
from nprt.proxies.encoding import N_INPUTS, depth_target, encode
from nprt.proxies.evaluate import evaluate, throughput
from nprt.proxies.export import export_onnx
from nprt.proxies.inference import Proxy
from nprt.proxies.model import ResidualMLP
from nprt.proxies.sampling import RaySamples, proxy_box, sample_rays
from nprt.scene.model import Mesh

log = logging.getLogger(__name__)

# Fixed, not the machine's core count: another count may reorder float sums. One thread:
# on 2 loaded cores, 2 OpenMP threads ran 13x slower than 1 (busy-waiting on each other).
TRAIN_THREADS = 1
# Wall-clock cap on the whole optimisation: a guard against a stalled machine, never the
# budget (default configs take well under a tenth of it on 2 cores).
SAFETY_CAP_S = 1800.0
# Cosine decay to this fraction of the learning rate over the budget.
LR_FLOOR = 0.05
# Share of the time budget given to the visibility net (it decides hit or miss).
VIS_SHARE = 0.6
# Calibration rays (neither training nor held-out) pick the visibility threshold.
CALIB_SEED_OFFSET = 2_000_003
THRESHOLDS = np.linspace(0.01, 0.99, 99)


def _fit(net, x, y, pools, loss_fn, config: ProxyConfig, steps: int, gen, desc: str,
         progress: bool, deadline: float) -> tuple[int, bool]:
    """Adam with cosine decay over `steps` mini-batches drawn from index pools at fixed shares.

    x : (n, k) float32 tensor; y : (n,) float32 tensor
    pools : list of ((m,) int64 tensor, share) -- the class ratio of every batch
    deadline : time.perf_counter() value past which training stops early (the safety cap)
    returns (steps taken, whether the safety cap stopped it)
    """
    pools = [(p, sh) for p, sh in pools if len(p) and sh > 0]
    if not pools:
        return 0, False
    total = sum(sh for _, sh in pools)
    per = [int(round(config.batch_size * sh / total)) for _, sh in pools]
    opt = torch.optim.Adam(net.parameters(), lr=config.lr)
    bar = tqdm(total=steps, desc=desc, unit="step", disable=not progress, leave=False)
    step = 0
    for step in range(steps):
        if time.perf_counter() > deadline:
            log.warning("%s: safety cap of %.0f s hit after %d of %d steps", desc, SAFETY_CAP_S,
                        step, steps)
            bar.close()
            return step, True
        frac = step / steps
        for g in opt.param_groups:
            g["lr"] = config.lr * (LR_FLOOR + (1 - LR_FLOOR) * 0.5 * (1 + math.cos(math.pi * frac)))
        idx = torch.cat([p[torch.randint(len(p), (k,), generator=gen)]
                         for (p, _), k in zip(pools, per, strict=True) if k > 0])
        loss = loss_fn(net(x[idx]), y[idx])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step % 100 == 99:
            bar.update(100)
            bar.set_postfix(loss=f"{loss.item():.4f}")
    bar.close()
    return steps, False


@contextlib.contextmanager
def _deterministic_torch(threads: int):
    """Deterministic kernels on a fixed thread count; restores torch's global state after."""
    before = (torch.get_num_threads(), torch.are_deterministic_algorithms_enabled())
    torch.set_num_threads(threads)
    torch.use_deterministic_algorithms(True)
    try:
        yield
    finally:
        torch.set_num_threads(before[0])
        torch.use_deterministic_algorithms(before[1])


def _calibrated_threshold(net, box, calib: RaySamples, config: ProxyConfig) -> float:
    """The visibility threshold with the best accuracy on calibration rays; a batch ratio
    other than the natural one shifts the net's outputs, and this shifts them back."""
    if not config.calibrate:
        return config.threshold
    with torch.no_grad():
        x = torch.from_numpy(encode(box, calib.points, calib.directions, config.encoding))
        vis = net(x).numpy()
    acc = [((vis >= thr) == calib.hit).mean() for thr in THRESHOLDS]
    best = np.flatnonzero(acc == np.max(acc))  # ties: the one nearest 0.5
    return float(THRESHOLDS[best[np.argmin(np.abs(THRESHOLDS[best] - 0.5))]])


def train_proxy(mesh: Mesh, config: ProxyConfig | None = None, progress: bool = True,
                geometry=None) -> Proxy:
    """Sample rays, train the visibility and depth nets, export to ONNX and score the
    result on held-out rays (seed + EVAL_SEED_OFFSET). The deterministic report lands in
    proxy.meta["report"]; wall-clock figures (train_s, sample_s, queries_per_s) in
    proxy.timing, which the blob does not hold."""
    config = config or ProxyConfig()
    with _deterministic_torch(TRAIN_THREADS):
        return _train(mesh, config, progress, geometry)


def _train(mesh: Mesh, config: ProxyConfig, progress: bool, geometry) -> Proxy:
    torch.manual_seed(config.seed)
    gen = torch.Generator().manual_seed(config.seed)
    if geometry is None:
        from nprt.workers.traversal.geometry import MeshGeometry

        geometry = MeshGeometry(mesh)
    t_start = time.perf_counter()
    s = sample_rays(mesh, config.n_samples, config.seed, config.grid, geometry)
    sample_s = time.perf_counter() - t_start
    box = proxy_box(mesh.bounds)
    n_in = N_INPUTS[config.encoding]
    x = torch.from_numpy(encode(box, s.points, s.directions, config.encoding))
    hit = torch.from_numpy(s.hit)
    hits, misses = torch.nonzero(hit).squeeze(1), torch.nonzero(~hit).squeeze(1)
    share = float(s.hit.mean()) if config.hit_share is None else config.hit_share
    name, w = mesh.name[:20], config.width
    vis_budget = max(1, int(round(VIS_SHARE * config.steps)))
    depth_budget = max(1, config.steps - vis_budget)

    t_train = time.perf_counter()
    deadline = t_train + SAFETY_CAP_S
    vis_net = ResidualMLP(n_in, w, config.blocks, sigmoid=True, fourier=config.fourier)
    vis_steps, capped_v = _fit(vis_net, x, hit.float(), [(hits, share), (misses, 1 - share)],
                               torch.nn.functional.mse_loss, config, vis_budget, gen,
                               f"{name} visibility N={w}", progress, deadline)
    depth_net = ResidualMLP(n_in, w, config.blocks, sigmoid=False, fourier=config.fourier)
    t_hit = np.where(s.hit, s.t, 0).astype(np.float32)
    depth_y = torch.from_numpy(depth_target(box, s.points, s.directions, t_hit, config.encoding))
    depth_steps, capped_d = _fit(depth_net, x, depth_y, [(hits, 1.0)],
                                 torch.nn.functional.l1_loss, config, depth_budget, gen,
                                 f"{name} depth N={w}", progress, deadline)
    train_s = time.perf_counter() - t_train
    calib = sample_rays(mesh, config.eval_samples, config.seed + CALIB_SEED_OFFSET,
                        config.grid, geometry)
    threshold = _calibrated_threshold(vis_net, box, calib, config)

    models = {"visibility": export_onnx(vis_net, n_in), "depth": export_onnx(depth_net, n_in)}
    meta = {
        "content_hash": mesh.content_hash,
        "mesh_name": mesh.name,
        "width": w,
        "blocks": config.blocks,
        "encoding": config.encoding,
        "bounds": np.asarray(mesh.bounds).tolist(),
        "box": box.tolist(),
        "diag": float(np.linalg.norm(box[1] - box[0])),
        "threshold": threshold,
        "config": config.to_dict(),
        "config_key": config.key,
    }
    report = evaluate(Proxy(meta, models), mesh, config.eval_samples,
                      config.seed + EVAL_SEED_OFFSET, config.grid, geometry, speed=False)
    report.update(train_samples=len(s), train_hit_fraction=float(s.hit.mean()),
                  vis_steps=vis_steps, depth_steps=depth_steps, capped=capped_v or capped_d,
                  train_threads=TRAIN_THREADS)
    meta["report"] = report
    proxy = Proxy(meta, models)
    proxy.timing = {"train_s": train_s, "sample_s": sample_s,
                    "queries_per_s": float(throughput(proxy))}
    log.info("trained proxy for %s: width %d, accuracy %.4f, %d + %d steps in %.1f s%s",
             mesh.name, w, report["accuracy"], vis_steps, depth_steps, train_s,
             " (SAFETY CAP HIT: not reproducible)" if report["capped"] else "")
    return proxy
