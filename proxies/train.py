"""Training both proxy nets on the CPU under a time and/or step budget (imports torch)."""

from __future__ import annotations

import logging
import math
import time

import numpy as np
import torch
from tqdm.auto import tqdm

from proxies.config import EVAL_SEED_OFFSET, ProxyConfig
from proxies.encoding import N_INPUTS, encode
from proxies.evaluate import evaluate
from proxies.export import export_onnx
from proxies.inference import Proxy
from proxies.model import ResidualMLP
from proxies.sampling import proxy_box, sample_rays
from scene.model import Mesh

log = logging.getLogger(__name__)

TRAIN_THREADS = 2
# Cosine decay to this fraction of LR over the budget: the last steps refine boundaries.
LR_FLOOR = 0.05
# Share of the time budget given to the visibility net (it decides hit or miss).
VIS_SHARE = 0.6


def _fit(net, x, y, pools, loss_fn, lr, budget_s, max_steps, batch, gen, bar_desc, progress):
    """Adam on mini-batches drawn equally from each index pool (the class ratio).

    x : (n, k) float32 tensor; y : (n,) float32 tensor; pools : list of (m,) int64 tensors
    returns the number of steps taken
    """
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    pools = [p for p in pools if len(p)]
    if not pools:
        return 0
    per = [batch // len(pools)] * len(pools)
    per[0] += batch - sum(per)
    t0, step = time.perf_counter(), 0
    bar = tqdm(total=100, desc=bar_desc, unit="%", disable=not progress, leave=False)
    while True:
        frac = (time.perf_counter() - t0) / budget_s if budget_s > 0 else 0.0
        if max_steps is not None:
            frac = max(frac, step / max_steps) if budget_s > 0 else step / max_steps
        if frac >= 1.0:
            break
        for g in opt.param_groups:
            g["lr"] = lr * (LR_FLOOR + (1 - LR_FLOOR) * 0.5 * (1 + math.cos(math.pi * frac)))
        idx = torch.cat([p[torch.randint(len(p), (k,), generator=gen)]
                         for p, k in zip(pools, per, strict=True)])
        loss = loss_fn(net(x[idx]), y[idx])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        if step % 50 == 0:
            bar.update(int(100 * min(frac, 1.0)) - bar.n)
            bar.set_postfix(loss=f"{loss.item():.4f}", step=step)
    bar.close()
    return step


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
        from workers.geometry import MeshGeometry

        geometry = MeshGeometry(mesh)
    t_start = time.perf_counter()
    s = sample_rays(mesh, config.n_samples, config.seed, config.grid, geometry)
    sample_s = time.perf_counter() - t_start
    box = proxy_box(mesh.bounds)
    diag = float(np.linalg.norm(box[1] - box[0]))
    n_in = N_INPUTS[config.encoding]
    x = torch.from_numpy(encode(box, s.points, s.directions, config.encoding))
    hit = torch.from_numpy(s.hit)
    hits, misses = torch.nonzero(hit).squeeze(1), torch.nonzero(~hit).squeeze(1)
    name = mesh.name[:20]

    t_train = time.perf_counter()
    vis_net = ResidualMLP(n_in, config.width, config.blocks, sigmoid=True)
    vis_steps = _fit(vis_net, x, hit.float(), [hits, misses], torch.nn.functional.mse_loss,
                     config.lr,
                     VIS_SHARE * config.budget_s, config.max_steps, config.batch_size, gen,
                     f"{name} visibility N={config.width}", progress)
    depth_net = ResidualMLP(n_in, config.width, config.blocks, sigmoid=False)
    depth_y = torch.from_numpy(np.where(s.hit, s.t / np.float32(diag), 0).astype(np.float32))
    depth_steps = _fit(depth_net, x, depth_y, [hits], torch.nn.functional.l1_loss, config.lr,
                       (1 - VIS_SHARE) * config.budget_s, config.max_steps, config.batch_size,
                       gen, f"{name} depth N={config.width}", progress)
    train_s = time.perf_counter() - t_train

    models = {"visibility": export_onnx(vis_net, n_in), "depth": export_onnx(depth_net, n_in)}
    meta = {
        "content_hash": mesh.content_hash,
        "mesh_name": mesh.name,
        "width": config.width,
        "blocks": config.blocks,
        "encoding": config.encoding,
        "bounds": np.asarray(mesh.bounds).tolist(),
        "box": box.tolist(),
        "diag": diag,
        "threshold": config.threshold,
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
    log.info("trained proxy for %s: width %d, accuracy %.4f, %.1f s", mesh.name,
             config.width, report["accuracy"], train_s)
    return Proxy(meta, models)
