"""Levers on held-out visibility accuracy that ProxyConfig does not expose (issue 11, item 2):
the loss, hard-example mining, and feature grids sampled along the ray, each against the
production visibility net (line encoding, 3 Fourier octaves, MSE) in one training loop.

Only the visibility net is trained: it alone decides hit or miss. Every variant sees the
same training rays (seed 0), the same number of steps and batch size, on one torch thread;
its threshold is calibrated on separate rays (as train.py does) and it is scored on the
held-out rays the proxy report uses. Smaller boxes are bench_proxy_cells; config knobs
(width, octaves, learning rate, blocks) are bench_proxy_thin and bench_proxy_calibrate.

    python -m bench.experiments.bench_proxy_levers [--mesh forest:default:pine] [--steps 3600]
    python -m bench.experiments.bench_proxy_levers --speed [--width 32]  # onnxruntime q/s

Appends rows to bench/results/proxy_levers.jsonl.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time

import numpy as np
import torch

from bench.common import RESULTS, smoke
from bench.experiments.bench_proxy_cells import find_mesh

# variant -> changes against the production visibility net
VARIANTS = {
    "production (line + Fourier 3, MSE)": {},
    "binary cross-entropy": {"loss": "bce"},
    "hard-example mining": {"mining": True},
    "grids along the ray, 8/16 x 2": {"grid": ([8, 16], 2)},
    "grids along the ray, 8/16/32 x 4": {"grid": ([8, 16, 32], 4)},
}
CHORD_POINTS = 8  # points sampled along the ray's chord through the box
N_IN = 6 + 3 * CHORD_POINTS  # line encoding, then the chord points
BATCH = 4096
# Mining: from MINE_START of the steps on, half of each batch comes from the MINE_TOP share
# of training rays with the largest error, re-ranked every MINE_EVERY steps.
MINE_START, MINE_TOP, MINE_EVERY = 0.2, 0.2, 500


class GatherGrid(torch.nn.Module):
    """One (r^3, features) grid read trilinearly by Gather ops, as onnxruntime would run it
    (torch's 3-D grid_sample has no ONNX export at opset 17): u (n, CHORD_POINTS, 3) in
    [-1, 1] -> (n, CHORD_POINTS * features)."""

    def __init__(self, r: int, features: int):
        super().__init__()
        self.r = r
        self.table = torch.nn.Parameter(1e-2 * torch.randn(r ** 3, features))
        corners = [[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)]
        self.register_buffer("corners", torch.tensor(corners, dtype=torch.float32))
        self.register_buffer("stride", torch.tensor([1.0, r, r * r]))

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        x = (u + 1) * (0.5 * (self.r - 1))
        x0 = torch.clamp(torch.floor(x), 0, self.r - 2)
        f = (x - x0).unsqueeze(2)  # (n, K, 1, 3)
        c = self.corners  # (8, 3)
        w = torch.prod(c * f + (1 - c) * (1 - f), dim=3)  # (n, K, 8) trilinear weights
        idx = ((x0.unsqueeze(2) + c) * self.stride).sum(3).long()  # (n, K, 8)
        return (self.table[idx] * w.unsqueeze(3)).sum(2).flatten(1)


class ChordGrids(torch.nn.Module):
    """Dense 3D feature grids at several resolutions, read trilinearly at CHORD_POINTS points
    along each ray's chord; their features (in ray order) join the line encoding.
    x (n, N_IN) float32 as `inputs` builds it -> (n,) visibility. Trained here and exported
    as is for the onnxruntime speed check."""

    def __init__(self, resolutions: list[int], features: int, width: int):
        from nprt.proxies.model import Fourier, ResidualMLP

        super().__init__()
        self.grids = torch.nn.ModuleList([GatherGrid(r, features) for r in resolutions])
        self.fourier = Fourier(3)
        n_in = CHORD_POINTS * features * len(resolutions) + 6 * 7
        self.mlp = ResidualMLP(n_in, width, 2, sigmoid=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        line, chord = x[:, :6], x[:, 6:].reshape(-1, CHORD_POINTS, 3)
        return self.mlp(torch.cat([*(g(chord) for g in self.grids), self.fourier(line)], 1))


def onnx_queries_per_s(net: torch.nn.Module, n_in: int) -> float:
    """Queries/s of one net in onnxruntime (2 threads, 4096 rows a call per thread, as
    nprt.proxies.inference runs proxies); weights are random: speed only."""
    from nprt.proxies.export import export_onnx
    from nprt.proxies.inference import ROWS_PER_THREAD, Proxy

    model = export_onnx(net, n_in)
    sess = Proxy({"box": np.zeros((2, 3)).tolist(), "diag": 1.0},
                 {"visibility": model, "depth": model}, threads=2).session("visibility")
    x = np.random.default_rng(0).uniform(-1, 1, (1 << 16, n_in)).astype(np.float32)
    chunk, best = 2 * ROWS_PER_THREAD, np.inf
    for _ in range(5):
        t0 = time.perf_counter()
        for s in range(0, len(x), chunk):
            sess.run(None, {"x": x[s:s + chunk]})
        best = min(best, time.perf_counter() - t0)
    return len(x) / best


class LineNet(torch.nn.Module):
    """The production visibility net; reads the line encoding, ignores the chord points."""

    def __init__(self, width: int):
        from nprt.proxies.model import ResidualMLP

        super().__init__()
        self.mlp = ResidualMLP(6, width, 2, sigmoid=True, fourier=3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.mlp(x[:, :6])


def inputs(box, s) -> torch.Tensor:
    """(n, N_IN) float32 of samples s: the line encoding (6), then the chord points
    (CHORD_POINTS x 3, in [-1, 1] box coordinates)."""
    from nprt.proxies.encoding import encode
    from nprt.proxies.sampling import box_exit

    p, d = s.points.astype(np.float64), s.directions.astype(np.float64)
    t = box_exit(box, p, d)[:, None] * (np.arange(CHORD_POINTS) + 0.5) / CHORD_POINTS
    pts = p[:, None, :] + t[..., None] * d[:, None, :]
    chord = (2 * (pts - box[0]) / (box[1] - box[0]) - 1).reshape(len(p), -1)
    line = encode(box, s.points, s.directions, "line")
    return torch.from_numpy(np.concatenate([line, chord], axis=1).astype(np.float32))


def predict(net, x) -> np.ndarray:
    with torch.no_grad():
        return torch.cat([net(x[i:i + 65536]) for i in range(0, len(x), 65536)]).numpy()


def train(net, x, y, steps: int, loss: str, mining: bool) -> None:
    """Adam, lr 2e-3 (1e-2 on grids), cosine decay to 5 %, as nprt.proxies.train does."""
    grids = [p for n, p in net.named_parameters() if n.startswith("grids")]
    rest = [p for n, p in net.named_parameters() if not n.startswith("grids")]
    groups = [{"params": rest, "lr": 2e-3}] + ([{"params": grids, "lr": 1e-2}] if grids else [])
    opt = torch.optim.Adam(groups)
    base = [g["lr"] for g in opt.param_groups]
    loss_fn = (torch.nn.functional.binary_cross_entropy if loss == "bce"
               else torch.nn.functional.mse_loss)
    gen = torch.Generator().manual_seed(0)
    hard = None
    for step in range(steps):
        frac = step / steps
        for g, lr in zip(opt.param_groups, base, strict=True):
            g["lr"] = lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * frac)))
        idx = torch.randint(len(y), (BATCH,), generator=gen)
        if mining and frac >= MINE_START:
            if hard is None or step % MINE_EVERY == 0:
                err = np.abs(predict(net, x) - y.numpy())
                hard = torch.from_numpy(np.argsort(-err, kind="stable")[:int(MINE_TOP * len(y))])
            idx[BATCH // 2:] = hard[torch.randint(len(hard), (BATCH - BATCH // 2,),
                                                  generator=gen)]
        out = loss_fn(net(x[idx]), y[idx])
        opt.zero_grad(set_to_none=True)
        out.backward()
        opt.step()


def run_mesh(spec: str, width: int, steps: int, samples: int, variants: list[str]) -> list:
    from nprt.proxies.config import EVAL_SEED_OFFSET
    from nprt.proxies.sampling import proxy_box, sample_rays
    from nprt.proxies.train import CALIB_SEED_OFFSET, THRESHOLDS
    from nprt.workers.traversal.geometry import MeshGeometry

    mesh = find_mesh(spec)
    geo, box = MeshGeometry(mesh), proxy_box(mesh.bounds)
    sets = {k: sample_rays(mesh, n, seed, 128, geo) for k, n, seed in
            (("train", samples, 0), ("calib", 1 << 16, CALIB_SEED_OFFSET),
             ("held", 1 << 16, EVAL_SEED_OFFSET))}
    x = {k: inputs(box, s) for k, s in sets.items()}
    y = torch.from_numpy(sets["train"].hit.astype(np.float32))
    rows = []
    for name in variants:
        v = VARIANTS[name]
        torch.manual_seed(0)
        net = ChordGrids(*v["grid"], width) if "grid" in v else LineNet(width)
        c0 = time.process_time()
        train(net, x["train"], y, steps, v.get("loss", "mse"), v.get("mining", False))
        cpu = time.process_time() - c0
        calib = predict(net, x["calib"])
        acc = [((calib >= t) == sets["calib"].hit).mean() for t in THRESHOLDS]
        thr = float(THRESHOLDS[int(np.argmax(acc))])
        held = predict(net, x["held"]) >= thr
        rows.append({"spec": spec, "triangles": len(mesh.faces), "mesh_bytes": mesh.nbytes,
                     "variant": name, "width": width, "steps": steps,
                     "accuracy": float((held == sets["held"].hit).mean()), "threshold": thr,
                     "params": int(sum(p.numel() for p in net.parameters())),
                     "train_cpu_s": cpu, "load": os.getloadavg()[0]})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mesh", nargs="+", default=["forest:default:pine"],
                    help="scene:size:mesh, e.g. family:small:sparse_foliage")
    ap.add_argument("--width", type=int, default=32)
    ap.add_argument("--steps", type=int, default=3600,
                    help="visibility steps (train.py gives it 60 %% of ProxyConfig.steps)")
    ap.add_argument("--samples", type=int, default=1 << 19)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--speed", action="store_true",
                    help="only time the chord-grid variants' visibility net in onnxruntime")
    ap.add_argument("--smoke", action="store_true",
                    help="a tiny pine, production and one grid variant, 20 steps (CI smoke test)")
    args = smoke(ap.parse_args(argv), mesh=["forest:tiny:pine"], steps=20, samples=1 << 12,
                 variants=[list(VARIANTS)[0], list(VARIANTS)[3]])
    torch.set_num_threads(1)
    if args.speed:
        from nprt.proxies.model import ResidualMLP

        torch.manual_seed(0)
        nets = {"production": (ResidualMLP(6, args.width, 2, True, fourier=3), 6)}
        nets.update({name: (ChordGrids(*v["grid"], args.width), N_IN)
                     for name, v in VARIANTS.items() if "grid" in v})
        for name, (net, n_in) in nets.items():
            qps = onnx_queries_per_s(net, n_in)
            print(f"{name}, width {args.width}: visibility net {qps / 1e6:.3f} M queries/s "
                  f"(load {os.getloadavg()[0]:.1f})")
        return
    RESULTS.mkdir(exist_ok=True)
    for spec in args.mesh:
        for row in run_mesh(spec, args.width, args.steps, args.samples, args.variants):
            with (RESULTS / "proxy_levers.jsonl").open("a") as f:
                f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
