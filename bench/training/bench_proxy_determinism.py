"""Proxy training is bit-reproducible whatever the load: train one small torus proxy and print
the blob's sha256 with the wall time, on the given number of training threads.

    python -m bench.training.bench_proxy_determinism [--threads 1]

Run it on an idle and on a loaded machine (or beside a busy process): the hash must match,
the time will not. A different --threads gives different bytes (summation order).
"""

from __future__ import annotations

import argparse
import hashlib
import os

from bench.common import RESULTS, finish, smoke


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.training.bench_proxy_determinism")
    ap.add_argument("--threads", type=int, default=None,
                    help="training threads (default: nprt.proxies.train.TRAIN_THREADS)")
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--smoke", action="store_true", help="40 steps, for the CI smoke test")
    args = smoke(ap.parse_args(argv), steps=40)
    import trimesh

    import nprt.proxies.train as train
    from nprt.proxies.config import ProxyConfig
    from nprt.scene.model import Mesh

    if args.threads is not None:
        train.TRAIN_THREADS = args.threads
    tm = trimesh.creation.torus(1.0, 0.3, major_sections=32, minor_sections=16)
    mesh = Mesh("torus", tm.vertices.astype("float32"), tm.faces.astype("uint32"))
    cfg = ProxyConfig(width=32, steps=args.steps, n_samples=1 << 15, grid=16, eval_samples=4096)
    p = train.train_proxy(mesh, cfg, progress=False)
    res = {"threads": train.TRAIN_THREADS, "steps": args.steps,
           "sha256": hashlib.sha256(p.to_bytes()).hexdigest(),
           "train_s": round(p.timing["train_s"], 2), "load": os.getloadavg()[0]}
    finish(res, RESULTS / f"proxy_determinism_t{train.TRAIN_THREADS}.json",
           markdown=lambda r: " ".join(f"{k} {v}" for k, v in r.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
