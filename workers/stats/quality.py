"""Image quality against a reference, on tone-mapped images as in the paper (section 6.1):
PSNR, SSIM (scikit-image) and mean FLIP (flip-evaluator, LDR)."""

from __future__ import annotations

import numpy as np

from nprt.workers.film import tonemap_srgb


def compare(reference: np.ndarray, test: np.ndarray) -> dict:
    """reference, test : (h, w, 3) float32 linear radiance -> {psnr_db, ssim, flip}."""
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    if reference.shape != test.shape:
        raise ValueError(f"image shapes differ: {reference.shape} vs {test.shape}")
    a = tonemap_srgb(reference).astype(np.float32) / 255.0
    b = tonemap_srgb(test).astype(np.float32) / 255.0
    if np.array_equal(a, b):
        psnr = float("inf")
    else:
        psnr = float(peak_signal_noise_ratio(a, b, data_range=1.0))
    ssim = float(structural_similarity(a, b, channel_axis=2, data_range=1.0))
    return {"psnr_db": psnr, "ssim": ssim, "flip": _flip(a, b)}


def _flip(a: np.ndarray, b: np.ndarray) -> float:
    import flip_evaluator

    _, mean, _ = flip_evaluator.evaluate(a, b, "LDR", inputsRGB=True, applyMagma=False)
    return float(mean)
