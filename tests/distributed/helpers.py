"""Shared settings, the relative image error, and image asserts that write the image, the
reference and the error map on failure."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import numpy as np

from nprt.workers.render import RenderResult, render
from nprt.workers.settings import RenderSettings
from nprt.workers.wavefront.batch import RayBatch, ShadowRayBatch

SCENES = ("forest", "city", "sculpture")
SIZE = "small"
REL_TOL = 1e-5  # exact mode differs from the reference only by float-summation order
# Small enough to stay fast, big enough that every ray kind crosses shards.
BASE = dict(width=48, height=32, spp=2, bounces=3, spp_per_pass=2, seed=7)


def settings(shards: int, **kw) -> RenderSettings:
    return RenderSettings(**{**BASE, **kw, "shards": shards})


def row_bytes(batch_type) -> int:
    """Bytes of one row of a batch type, from its declared dtype layout."""
    total = 0
    for f in fields(batch_type):
        width, dtype = batch_type._SPEC[f.name]
        total += np.dtype(dtype).itemsize * (width or 1)
    return total


RAY_ROW_BYTES = row_bytes(RayBatch)
SHADOW_ROW_BYTES = row_bytes(ShadowRayBatch)


def rel_error(img: np.ndarray, ref: np.ndarray) -> float:
    """max |img - ref| / max |ref| over all pixels and channels."""
    scale = float(np.abs(ref).max())
    if scale == 0.0:
        raise ValueError("reference image is black; the relative error is undefined")
    return float(np.abs(img.astype(np.float64) - ref).max() / scale)


def _png(img: np.ndarray, scale: float, path: Path) -> None:
    from PIL import Image

    x = np.clip(np.nan_to_num(img / max(scale, 1e-30)), 0.0, 1.0)
    Image.fromarray((x * 255 + 0.5).astype(np.uint8)).save(path)


def dump_images(tmp_path: Path, name: str, img: np.ndarray, ref: np.ndarray) -> Path:
    """Write image and reference (scaled by the reference's max) and the error map
    (|img - ref| / max |ref| / REL_TOL, so 1 = at the limit) as PNGs."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import cm
    from PIL import Image

    scale = float(np.abs(ref).max()) or 1.0
    _png(img, scale, tmp_path / f"{name}_image.png")
    _png(ref, scale, tmp_path / f"{name}_reference.png")
    err = (np.abs(img.astype(np.float64) - ref) / scale / REL_TOL).max(axis=-1)
    e = np.clip(np.nan_to_num(err, nan=1.0, posinf=1.0), 0.0, 1.0)
    Image.fromarray((cm.inferno(e)[..., :3] * 255).astype(np.uint8)).save(
        tmp_path / f"{name}_error.png")
    return tmp_path


def assert_matches(tmp_path: Path, name: str, img: np.ndarray, ref: np.ndarray) -> None:
    err = rel_error(img, ref)
    if not err <= REL_TOL:
        where = dump_images(tmp_path, name, img, ref)
        raise AssertionError(f"{name}: relative error {err:.3g} > {REL_TOL:g}; "
                             f"image, reference and error map in {where}")


def assert_identical(tmp_path: Path, name: str, result: RenderResult,
                     ref: RenderResult) -> None:
    """The film sums (float64) are the same bits: exact mode's promise at any K."""
    got, want = result.film.sums, ref.film.sums
    if not np.array_equal(got, want):
        where = dump_images(tmp_path, name, result.film.image(), ref.film.image())
        diff = np.abs(got - want)
        raise AssertionError(f"{name}: {np.count_nonzero(diff)} film sums differ from the "
                             f"reference (largest {diff.max():.3g}); images in {where}")


def reference(scene, s: RenderSettings) -> RenderResult:
    return render(scene, s.model_copy(update={"shards": 0}))


def _refuse(*a, **kw):
    raise AssertionError("the driver read a mesh")


def refuse_mesh_reads(monkeypatch) -> None:
    """From now on any mesh read in this (the driver's) process fails the test; shard
    actors and training tasks are other processes and load theirs as usual."""
    from nprt.scene import json_load
    from nprt.scene.store import DirectorySource

    monkeypatch.setattr(json_load, "read_mesh_file", _refuse)
    monkeypatch.setattr(json_load, "build_mesh", _refuse)
    monkeypatch.setattr(DirectorySource, "_load", _refuse)
