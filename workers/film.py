"""The framebuffer: float64 radiance sums per pixel, and image output (linear EXR, sRGB PNG)."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
from PIL import Image

ACCUM_DTYPE = np.float64


class Film:
    """sums : (height * width, 3) float64 radiance summed over samples;
    samples : (height * width,) int64 samples accumulated per pixel."""

    def __init__(self, width: int, height: int):
        self.width, self.height = width, height
        self.sums = np.zeros((width * height, 3), ACCUM_DTYPE)
        self.samples = np.zeros(width * height, np.int64)
        self.lock = threading.Lock()  # readers of a live film (the service) take it too

    def image(self) -> np.ndarray:
        """(height, width, 3) float32 linear radiance, mean over accumulated samples."""
        div = np.maximum(self.samples, 1)[:, None]
        return (self.sums / div).astype(np.float32).reshape(self.height, self.width, 3)

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        save_image(self.image(), path)
        return path


def tonemap_srgb(img: np.ndarray) -> np.ndarray:
    """(h, w, 3) linear float -> (h, w, 3) uint8 sRGB (clamped, no exposure curve)."""
    x = np.clip(np.nan_to_num(img, nan=0.0, posinf=1.0), 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return (srgb * 255.0 + 0.5).astype(np.uint8)


def save_image(img: np.ndarray, path: Path) -> None:
    """Write by extension: .exr is linear float32, anything else an sRGB 8-bit image."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".exr":
        write_exr(img, path)
    else:
        Image.fromarray(tonemap_srgb(img)).save(path)


def write_exr(img: np.ndarray, path: Path) -> None:
    import OpenEXR

    rgb = np.ascontiguousarray(img, dtype=np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"RGB": rgb}) as f:
        f.write(str(path))


def read_exr(path: Path) -> np.ndarray:
    """(h, w, 3) float32 linear RGB."""
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        return np.asarray(f.channels()["RGB"].pixels, dtype=np.float32)
