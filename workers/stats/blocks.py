"""Block statistics for "the same image within noise": 8x8-pixel block means, their mean
relative error, and per-block z-scores with standard errors estimated from two seeds.

Averaging a block removes most of the per-pixel noise while a bias (a lost shadow, a
light leak) survives, so block errors separate numerical drift from sampling noise.
"""

from __future__ import annotations

import numpy as np

BLOCK_PX = 8
# Relative floor of a block's standard error: where the two seeds agree exactly (a
# constant sky seen directly) the estimated noise is zero, and float rounding of a moved
# scene, about 1e-7 relative, must not count as a difference.
SIGMA_FLOOR_REL = 1e-4


def block_means(img: np.ndarray, block: int = BLOCK_PX) -> np.ndarray:
    """(h, w, c) image -> (h // block, w // block, c) float64 block means (a ragged
    border is dropped)."""
    img = np.asarray(img, np.float64)
    h, w = (img.shape[0] // block) * block, (img.shape[1] // block) * block
    if h == 0 or w == 0:
        raise ValueError(f"image {img.shape[:2]} is smaller than one {block}x{block} block")
    c = img.shape[2]
    return img[:h, :w].reshape(h // block, block, w // block, block, c).mean(axis=(1, 3))


def block_error(img: np.ndarray, ref: np.ndarray, block: int = BLOCK_PX) -> float:
    """Mean |block(img) - block(ref)| over blocks and channels, relative to the mean
    |block(ref)|."""
    a, b = block_means(img, block), block_means(ref, block)
    scale = float(np.abs(b).mean())
    if scale == 0.0:
        raise ValueError("reference image is black; the relative block error is undefined")
    return float(np.abs(a - b).mean() / scale)


def block_sigma(ref: np.ndarray, ref2: np.ndarray, block: int = BLOCK_PX) -> np.ndarray:
    """(h // block, w // block, c) standard error of one render's block mean, from two
    renders that differ only in their seed: each pixel's variance is estimated as
    (x1 - x2)^2 / 2, and the block mean's variance is their sum over the block / block^4
    (pixels are independent), which pools block^2 estimates into each block's."""
    d = np.asarray(ref, np.float64) - np.asarray(ref2, np.float64)
    var_px = 0.5 * d * d
    return np.sqrt(block_means(var_px, block) / (block * block))


def block_z(img: np.ndarray, ref: np.ndarray, ref2: np.ndarray,
            block: int = BLOCK_PX) -> np.ndarray:
    """(h // block, w // block, c) z-scores of img's blocks against ref's, taking img and
    ref as independent renders at ref's noise level (ref2: ref with another seed); the
    standard error is floored at SIGMA_FLOOR_REL of the block's value. A block that is
    black in ref and ref2 scores 0 where img agrees and inf where it does not."""
    mean = block_means(ref, block)
    diff = block_means(img, block) - mean
    sigma = np.hypot(np.sqrt(2.0) * block_sigma(ref, ref2, block), SIGMA_FLOOR_REL * mean)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(sigma > 0, diff / sigma, np.where(diff == 0, 0.0, np.inf))
