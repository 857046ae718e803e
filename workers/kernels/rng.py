"""Counter-based RNG: every random number is a pure hash of
(seed, pixel, sample, bounce, dimension), so images depend on neither batch
size, batch order, nor which shard evaluates a ray."""

from __future__ import annotations

import numpy as np

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_S30, _S27, _S31 = np.uint64(30), np.uint64(27), np.uint64(31)

# Dimension layout within one bounce. Camera jitter uses bounce index CAMERA_BOUNCE.
DIM_BSDF_U, DIM_BSDF_V, DIM_RR = 0, 1, 2
DIM_LIGHT_BASE = 3  # shadow ray s uses dims DIM_LIGHT_BASE + 3*s + {0: light pick, 1: u, 2: v}
CAMERA_BOUNCE = 255


def _mix(x: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser, (n,) uint64 -> (n,) uint64 (wrapping arithmetic)."""
    x = (x ^ (x >> _S30)) * _M1
    x = (x ^ (x >> _S27)) * _M2
    return x ^ (x >> _S31)


def uniform(seed: int, pixel: np.ndarray, sample: np.ndarray, bounce, dim) -> np.ndarray:
    """Uniform numbers in [0, 1).

    pixel  : (n,) uint32
    sample : (n,) uint32
    bounce : int or (n,) uint8
    dim    : int or (n,) int
    returns (n,) float64
    """
    with np.errstate(over="ignore"):
        key = _mix(np.uint64(seed & 0xFFFFFFFFFFFFFFFF)
                   + _GOLDEN * (np.asarray(dim, dtype=np.uint64) + np.uint64(1)))
        x = key ^ (pixel.astype(np.uint64) << np.uint64(32)) ^ sample.astype(np.uint64)
        x = _mix(x)
        x = _mix(x ^ (np.asarray(bounce, dtype=np.uint64) * _GOLDEN))
    return (x >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))
