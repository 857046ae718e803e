"""Counter-based RNG: every random number is a pure hash of
(seed, pixel, sample, bounce, dimension), so images depend on neither batch
size, batch order, nor which shard evaluates a ray. The hash (splitmix64's finaliser) is
defined once, here, in compiled code; the shading kernels inline `uniform_keyed`, and
tests/workers/oracles.py keeps a numpy copy to check it against (through the compiled
row loops of tests/workers/rng_rows.py: no render calls a loop of its own here, so a kernel
here would never be compiled by a render and would look uncached to nprt.workers.jitcache
forever)."""

from __future__ import annotations

import numpy as np
from numba import njit

# Dimension layout within one bounce. Camera jitter uses bounce index CAMERA_BOUNCE.
DIM_BSDF_U, DIM_BSDF_V, DIM_RR = 0, 1, 2
DIM_LIGHT_BASE = 3  # shadow ray s uses dims DIM_LIGHT_BASE + 3*s + {0: light pick, 1: u, 2: v}
CAMERA_BOUNCE = 255

# error_model="numpy" as in every kernel module.
JIT = {"cache": True, "nogil": True, "error_model": "numpy"}

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_TO_UNIT = 1.0 / (1 << 53)


@njit(inline="always", **JIT)
def _mix(x):
    """splitmix64 finaliser on a uint64 (wrapping)."""
    x = (x ^ (x >> np.uint64(30))) * _M1
    x = (x ^ (x >> np.uint64(27))) * _M2
    return x ^ (x >> np.uint64(31))


@njit(inline="always", **JIT)
def dim_key(seed, dim):
    """The per-(seed, dimension) key of `uniform`; seed and dim uint64."""
    return _mix(seed + _GOLDEN * (dim + np.uint64(1)))


@njit(inline="always", **JIT)
def uniform_keyed(key, pixel, sample, bounce):
    """`uniform` for one row, given its dimension's key (uint64)."""
    x = key ^ (np.uint64(pixel) << np.uint64(32)) ^ np.uint64(sample)
    x = _mix(x)
    x = _mix(x ^ (np.uint64(bounce) * _GOLDEN))
    return np.float64(x >> np.uint64(11)) * _TO_UNIT
