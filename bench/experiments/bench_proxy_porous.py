"""Porous geometry in the proxy (issue 21, item 4): two levers no earlier round measured, on
the foliage scene's leaf clouds (scene/demos/family.build_foliage), against the production
visibility net in bench_proxy_levers' training loop (same rays budget, steps, seed, one
torch thread; threshold calibrated on separate uniform rays; scored on the proxy report's
held-out rays).

- grazing-ray sampling: half the training rays are drawn from "grazing" rays, those whose
  label flips under a small jitter of origin and direction (they pass a leaf's edge);
- a per-box visibility prior: the net predicts a logit added to the logit of
  1 - exp(-sigma L), L the ray's chord through the box and sigma fitted on the training rays
  (a leaf cloud as a homogeneous absorbing medium), instead of the visibility itself.

    python -m bench.experiments.bench_proxy_porous [--mesh foliage:default:leafy] [--steps 3600]

Appends rows to bench/results/proxy_porous.jsonl (--smoke: a tiny run, written elsewhere).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import torch

from bench.common import RESULTS, add_output_flags, smoke
from bench.experiments.bench_proxy_levers import LineNet, inputs, predict, train

VARIANTS = ("production", "grazing-ray sampling", "per-box visibility prior")
JITTER = 0.01  # of the box diagonal (origin) and radians (direction): about a leaf's width
GRAZING_SHARE = 0.5


class PriorNet(torch.nn.Module):
    """sigmoid(MLP logit of the line encoding + logit of the absorbing-medium prior); the
    prior's logit is the input's last column."""

    def __init__(self, width: int):
        from nprt.proxies.model import ResidualMLP

        super().__init__()
        self.mlp = ResidualMLP(6, width, 2, sigmoid=False, fourier=3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.mlp(x[:, :6]) + x[:, -1])


def find_mesh(spec: str):
    """'foliage:default:leafy', or a demo / family mesh as bench_proxy_cells names them."""
    from bench.experiments.bench_proxy_cells import find_mesh as other
    from nprt.scene.demos import family

    scene, size, name = spec.split(":")
    if scene != "foliage":
        return other(spec)
    return next(m for m in family.foliage_meshes(size) if m.name == name)


def grazing(mesh, geo, box, n: int, seed: int):
    """(n,) RaySamples drawn from rays whose hit label flips under a jitter of JITTER (fewer
    where 16 rounds of 4n candidates hold fewer)."""
    from nprt.proxies.sampling import RaySamples, label, sample_rays

    rng = np.random.default_rng(seed)
    diag = float(np.linalg.norm(box[1] - box[0]))
    fields = ("points", "directions", "hit", "t")
    found = {f: [] for f in fields}
    total = 0
    for round_ in range(16):
        s = sample_rays(mesh, 4 * n, seed + 7919 * (round_ + 1), 128, geo)
        d = s.directions + rng.normal(0, JITTER, s.directions.shape)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        p = np.clip(s.points + rng.normal(0, JITTER * diag, s.points.shape), box[0], box[1])
        flip = label(geo, box, p, d).hit != s.hit  # (4n,) bool: the ray grazes a leaf
        for f in fields:
            found[f].append(getattr(s, f)[flip])
        total += int(flip.sum())
        if total >= n:
            break
    return RaySamples(*(np.concatenate(found[f])[:n] for f in fields))


def prior_logit(box, s, sigma: float) -> np.ndarray:
    """(n,) float32 logit of 1 - exp(-sigma L), L each ray's chord through the box."""
    from nprt.proxies.sampling import box_exit

    chord = box_exit(box, s.points.astype(np.float64), s.directions.astype(np.float64))
    p = np.clip(1 - np.exp(-sigma * chord), 1e-4, 1 - 1e-4)
    return np.log(p / (1 - p)).astype(np.float32)


def fit_sigma(box, s) -> float:
    """Absorption per unit chord that matches the training rays' hit fraction by chord."""
    from nprt.proxies.sampling import box_exit

    chord = box_exit(box, s.points.astype(np.float64), s.directions.astype(np.float64))
    grid = np.geomspace(1e-3, 1e2, 400)
    err = [np.mean((1 - np.exp(-g * chord) - s.hit) ** 2) for g in grid]
    return float(grid[int(np.argmin(err))])


def run_mesh(spec: str, width: int, steps: int, samples: int, variants) -> list[dict]:
    from nprt.proxies.config import EVAL_SEED_OFFSET
    from nprt.proxies.sampling import RaySamples, proxy_box, sample_rays
    from nprt.proxies.train import CALIB_SEED_OFFSET, THRESHOLDS
    from nprt.workers.traversal.geometry import MeshGeometry

    mesh = find_mesh(spec)
    geo, box = MeshGeometry(mesh), proxy_box(mesh.bounds)
    sets = {k: sample_rays(mesh, n, seed, 128, geo) for k, n, seed in
            (("train", samples, 0), ("calib", 1 << 16, CALIB_SEED_OFFSET),
             ("held", 1 << 16, EVAL_SEED_OFFSET))}
    sigma = fit_sigma(box, sets["train"])
    rows = []
    for name in variants:
        train_set = sets["train"]
        if name == "grazing-ray sampling":
            k = int(GRAZING_SHARE * samples)
            g = grazing(mesh, geo, box, k, 1)
            u = sets["train"]
            train_set = RaySamples(*(np.concatenate([getattr(u, f)[:samples - len(g.hit)],
                                                     getattr(g, f)])
                                     for f in ("points", "directions", "hit", "t")))
        x = {k: inputs(box, s) for k, s in (("train", train_set), ("calib", sets["calib"]),
                                            ("held", sets["held"]))}
        if name == "per-box visibility prior":
            x = {k: torch.cat([v, torch.from_numpy(prior_logit(
                box, train_set if k == "train" else sets[k], sigma))[:, None]], 1)
                for k, v in x.items()}
        y = torch.from_numpy(train_set.hit.astype(np.float32))
        torch.manual_seed(0)
        net = PriorNet(width) if name == "per-box visibility prior" else LineNet(width)
        c0 = time.process_time()
        train(net, x["train"], y, steps, "mse", False)
        cpu = time.process_time() - c0
        calib = predict(net, x["calib"])
        acc = [((calib >= t) == sets["calib"].hit).mean() for t in THRESHOLDS]
        thr = float(THRESHOLDS[int(np.argmax(acc))])
        held = predict(net, x["held"]) >= thr
        rows.append({"spec": spec, "variant": name, "width": width, "steps": steps,
                     "samples": samples, "accuracy": float((held == sets["held"].hit).mean()),
                     "threshold": thr, "sigma": sigma,
                     "grazing_share_of_train": float(GRAZING_SHARE
                                                     if name.startswith("grazing") else 0.0),
                     "train_cpu_s": round(cpu, 2), "load": os.getloadavg()[0]})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.experiments.bench_proxy_porous",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--mesh", nargs="+",
                    default=["foliage:default:leafy", "foliage:default:leafy_sparse"])
    ap.add_argument("--width", type=int, default=32)
    ap.add_argument("--steps", type=int, default=3600,
                    help="visibility steps (train.py gives it 60 %% of ProxyConfig.steps)")
    ap.add_argument("--samples", type=int, default=1 << 19)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    add_output_flags(ap, RESULTS)
    args = smoke(ap.parse_args(argv), mesh=["foliage:tiny:leafy"], steps=20, samples=4096)
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    for spec in args.mesh:
        for row in run_mesh(spec, args.width, args.steps, args.samples, args.variants):
            with (args.out / "proxy_porous.jsonl").open("a") as f:
                f.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
