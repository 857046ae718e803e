"""Encode a film snapshot (sums + sample counts) as PNG or EXR bytes, whole or one tile."""

from __future__ import annotations

import io
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

from nprt.workers.film import Film, tonemap_srgb, write_exr


def film_image(sums: np.ndarray, samples: np.ndarray, width: int, height: int) -> np.ndarray:
    """sums : (h * w, 3) float64, samples : (h * w,) int64 -> (h, w, 3) float32 linear,
    through Film.image() itself so PNGs match a direct render bit for bit."""
    film = Film(width, height)
    film.sums, film.samples = sums, samples
    return film.image()


def png_bytes(img: np.ndarray) -> bytes:
    """img : (h, w, 3) float32 linear -> sRGB 8-bit PNG."""
    buf = io.BytesIO()
    Image.fromarray(tonemap_srgb(img)).save(buf, format="PNG")
    return buf.getvalue()


def exr_bytes(img: np.ndarray) -> bytes:
    """img : (h, w, 3) float32 linear -> OpenEXR (the library writes to paths only)."""
    with tempfile.TemporaryDirectory(prefix="nprt-exr-") as d:
        path = Path(d) / "image.exr"
        write_exr(img, path)
        return path.read_bytes()


def f16_bytes(img: np.ndarray) -> bytes:
    """img : (h, w, 3) float32 linear -> little-endian float16 bytes, row-major, for the
    dashboard (it applies exposure to linear values); clipped to float16's largest finite
    value so an outlier is bright, not infinite."""
    return np.clip(img, 0.0, 65504.0).astype("<f2").tobytes()


def encode(img: np.ndarray, fmt: str) -> bytes:
    if fmt == "png":
        return png_bytes(img)
    if fmt == "exr":
        return exr_bytes(img)
    raise ValueError(f"unknown image format {fmt!r}; expected 'png' or 'exr'")
