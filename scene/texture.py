"""Textures: images (sRGB) and .npy arrays (linear) read as (h, w, 3) float32 linear."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nprt.scene.errors import SceneError
from nprt.scene.paths import FileRefs

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """c : (..., 3) float in [0, 1], sRGB encoded -> linear, same shape, float32."""
    c = np.asarray(c, dtype=np.float32)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def read_texture(path: Path, where: str, refs: FileRefs | None = None) -> np.ndarray:
    """An image (sRGB) or .npy (linear) as texture : (h, w, 3) float32 linear; `path`
    comes from `refs.resolve`."""
    shown = (refs or FileRefs(path.parent)).show(path)
    try:
        if path.suffix.lower() == ".npy":
            tex = np.load(path, allow_pickle=False).astype(np.float32)
        else:
            from PIL import Image

            with Image.open(path) as img:
                tex = srgb_to_linear(np.asarray(img.convert("RGB"), dtype=np.float32) / 255.0)
    except Exception as e:  # PIL/numpy raise many types for bad files
        raise SceneError(f"{where}: could not read texture {shown}: {e}") from None
    if tex.ndim != 3 or tex.shape[2] != 3 or tex.shape[0] == 0 or tex.shape[1] == 0:
        raise SceneError(f"{where}: texture {shown} must have shape (h, w, 3), got {tex.shape}")
    if not np.isfinite(tex).all():
        raise SceneError(f"{where}: texture {shown} has non-finite texels")
    return np.ascontiguousarray(tex)
