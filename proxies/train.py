"""Training both proxy nets on the CPU under a time and/or step budget (imports torch)."""

from __future__ import annotations

import logging
import math
import time

import numpy as np
import torch
from tqdm.auto import tqdm

from nprt.proxies.config import EVAL_SEED_OFFSET, ProxyConfig
from nprt.proxies.encoding import N_INPUTS, depth_target, encode
from nprt.proxies.evaluate import evaluate
from nprt.proxies.export import export_onnx
from nprt.proxies.inference import Proxy
from nprt.proxies.model import ResidualMLP
from nprt.proxies.sampling import RaySamples, proxy_box, sample_rays
from nprt.scene.model import Mesh

log = logging.getLogger(__name__)

TRAIN_THREADS = 2
# Cosine decay to this fraction of the learning rate over the budget.
LR_FLOOR = 0.05
# Share of the time budget given to the visibility net (it decides hit or miss).
VIS_SHARE = 0.6
# Calibration rays (neither training nor held-out) pick the visibility threshold.
CALIB_SEED_OFFSET = 2_000_003
THRESHOLDS = np.linspace(0.01, 0.99, 99)


def _fit(net, x, y, pools, loss_fn, config: ProxyConfig, budget_s: float, gen, desc: str,
         progress: bool) -> int:
    """Adam with cosine decay on mini-batches drawn from index pools at fixed shares.

    x : (n, k) float32 tensor; y : (n,) float32 tensor
    pools : list of ((m,) int64 tensor, share) -- the class ratio of every batch
    returns the number of steps taken
    """
    pools = [(p, sh) for p, sh in pools if len(p) and sh > 0]
    if not pools:
        return 0
    total = sum(sh for _, sh in pools)
    per = [int(round(config.batch_size * sh / total)) for _, sh in pools]
    opt = torch.optim.Adam(net.parameters(), lr=config.lr)
    t0, step = time.perf_counter(), 0
    bar = tqdm(total=100, desc=desc, unit="%", disable=not progress, leave=False)
    while True:
        frac = (time.perf_counter() - t0) / budget_s if budget_s > 0 else 0.0
        if config.max_steps is not None:
            frac = max(frac, step / max(1, config.max_steps))
        if frac >= 1.0:
            break
        for g in opt.param_groups:
            g["lr"] = config.lr * (LR_FLOOR + (1 - LR_FLOOR) * 0.5 * (1 + math.cos(math.pi * frac)))
        idx = torch.cat([p[torch.randint(len(p), (k,), generator=gen)]
                         for (p, _), k in zip(pools, per, strict=True) if k > 0])
        loss = loss_fn(net(x[idx]), y[idx])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        if step % 25 == 0:
            bar.update(int(100 * min(frac, 1.0)) - bar.n)
            bar.set_postfix(loss=f"{loss.item():.4f}", step=step)
    bar.close()
    return step


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
                geometry=None, threads: int = TRAIN_THREADS) -> Proxy:
    """Sample rays, train the visibility and depth nets, export to ONNX and score the
    result on held-out rays (seed + EVAL_SEED_OFFSET). The report lands in proxy.meta."""
    config = config or ProxyConfig()
    if config.budget_s <= 0 and config.max_steps is None:
        raise ValueError("training needs budget_s > 0 or max_steps")
    torch.set_num_threads(threads)
    torch.manual_seed(config.seed)
    gen = torch.Generator().manual_seed(config.seed)
    if geometry is None:
        from nprt.workers.geometry import MeshGeometry

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

    t_train = time.perf_counter()
    vis_net = ResidualMLP(n_in, w, config.blocks, sigmoid=True, fourier=config.fourier)
    vis_steps = _fit(vis_net, x, hit.float(), [(hits, share), (misses, 1 - share)],
                     torch.nn.functional.mse_loss, config, VIS_SHARE * config.budget_s, gen,
                     f"{name} visibility N={w}", progress)
    depth_net = ResidualMLP(n_in, w, config.blocks, sigmoid=False, fourier=config.fourier)
    t_hit = np.where(s.hit, s.t, 0).astype(np.float32)
    depth_y = torch.from_numpy(depth_target(box, s.points, s.directions, t_hit, config.encoding))
    depth_steps = _fit(depth_net, x, depth_y, [(hits, 1.0)], torch.nn.functional.l1_loss,
                       config, (1 - VIS_SHARE) * config.budget_s, gen, f"{name} depth N={w}",
                       progress)
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
    proxy = Proxy(meta, models)
    report = evaluate(proxy, mesh, config.eval_samples, config.seed + EVAL_SEED_OFFSET,
                      config.grid, geometry)
    report.update(train_s=train_s, sample_s=sample_s, train_samples=len(s),
                  train_hit_fraction=float(s.hit.mean()), vis_steps=vis_steps,
                  depth_steps=depth_steps)
    meta["report"] = report
    log.info("trained proxy for %s: width %d, accuracy %.4f, %.1f s", mesh.name, w,
             report["accuracy"], train_s)
    return Proxy(meta, models)
