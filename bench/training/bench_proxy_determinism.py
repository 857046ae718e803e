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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.training.bench_proxy_determinism")
    ap.add_argument("--threads", type=int, default=None,
                    help="training threads (default: nprt.proxies.train.TRAIN_THREADS)")
    args = ap.parse_args(argv)
    import trimesh

    import nprt.proxies.train as train
    from nprt.proxies.config import ProxyConfig
    from nprt.scene.model import Mesh

    if args.threads is not None:
        train.TRAIN_THREADS = args.threads
    tm = trimesh.creation.torus(1.0, 0.3, major_sections=32, minor_sections=16)
    mesh = Mesh("torus", tm.vertices.astype("float32"), tm.faces.astype("uint32"))
    cfg = ProxyConfig(width=32, steps=400, n_samples=1 << 15, grid=16, eval_samples=4096)
    p = train.train_proxy(mesh, cfg, progress=False)
    print(f"threads {train.TRAIN_THREADS} sha256 {hashlib.sha256(p.to_bytes()).hexdigest()} "
          f"train_s {p.timing['train_s']:.2f} load {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
