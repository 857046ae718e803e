"""Shared builders for the workers tests: analytic scenes, renders, and image asserts
that write the image, the reference and the error map on failure."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from nprt.scene.model import Camera, Environment, Instance, Material, Mesh, Scene
from nprt.workers.render import render
from nprt.workers.settings import RenderSettings


def mesh_from_trimesh(tm: trimesh.Trimesh, name: str = "mesh", material: int = 0) -> Mesh:
    """Flat-shaded Mesh (no vertex normals, so shading normal == geometric normal)."""
    return Mesh(name, np.asarray(tm.vertices, np.float32), np.asarray(tm.faces, np.uint32),
                material=material)


def plane_mesh(half: float = 10.0, divisions: int = 1, name: str = "plane",
               material: int = 0) -> Mesh:
    """Square in the y = 0 plane, [-half, half]^2 in x and z, `divisions`^2 quads."""
    g = np.linspace(-half, half, divisions + 1)
    xs, zs = np.meshgrid(g, g, indexing="ij")
    verts = np.stack([xs.ravel(), np.zeros(xs.size), zs.ravel()], axis=1)
    k = divisions + 1
    i, j = np.mgrid[0:divisions, 0:divisions]
    a = (i * k + j).ravel()
    b, c, d = a + k, a + k + 1, a + 1
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return Mesh(name, verts.astype(np.float32), faces.astype(np.uint32), material=material)


def single(mesh: Mesh, transform=None, **kw) -> Scene:
    """A scene holding one instance of one mesh."""
    xf = np.eye(4) if transform is None else np.asarray(transform, np.float64)
    return Scene((mesh,), (Instance(0, xf),), **kw)


def trs(translate=(0, 0, 0), scale=1.0, axis=(0, 0, 1), angle_deg=0.0) -> np.ndarray:
    """(4, 4) float64 local -> world: scale, then rotate about axis, then translate."""
    r = trimesh.transformations.rotation_matrix(np.radians(angle_deg), axis)
    s = np.diag(np.r_[np.broadcast_to(np.asarray(scale, float), 3), 1.0])
    t = trimesh.transformations.translation_matrix(translate)
    return t @ r @ s


def down_camera(height: float, fov_deg: float) -> Camera:
    """Camera `height` above the origin looking down -y; image right is +x, top is -z."""
    return Camera(eye=(0.0, height, 0.0), target=(0.0, 0.0, 0.0), up=(0.0, 0.0, -1.0),
                  fov_deg=fov_deg)


def plane_points_seen(width: int, height: int, cam_height: float, fov_deg: float,
                      sub: int = 8) -> np.ndarray:
    """(height, width, sub*sub, 3) float64 points of the plane y = 0 that `down_camera` sees
    through a sub x sub grid in each pixel. Independent pinhole geometry: NDC x =
    (col + jx) / width * 2 - 1 along +x, NDC y = 1 - (row + jy) / height * 2 along -z,
    and the ray reaches y = 0 after cam_height units of -y."""
    half_h = np.tan(np.radians(fov_deg) / 2)
    half_w = half_h * width / height
    j = (np.arange(sub) + 0.5) / sub
    col = np.arange(width)[None, :, None, None] + j[None, None, None, :]  # (1, w, 1, sub)
    row = np.arange(height)[:, None, None, None] + j[None, None, :, None]  # (h, 1, sub, 1)
    x = ((col / width) * 2 - 1) * half_w * cam_height
    z = -(1 - (row / height) * 2) * half_h * cam_height
    x, z = np.broadcast_arrays(x, z)  # (h, w, sub, sub)
    return np.stack([x, np.zeros_like(x), z], axis=-1).reshape(height, width, sub * sub, 3)


def render_image(scene: Scene, **settings) -> np.ndarray:
    """(h, w, 3) float32 mean radiance from the reference renderer."""
    return render(scene, RenderSettings(**settings)).film.image()


def _to_png(img: np.ndarray, scale: float, path: Path) -> None:
    from PIL import Image

    x = np.clip(np.nan_to_num(img / max(scale, 1e-30)), 0.0, 1.0)
    Image.fromarray((x * 255 + 0.5).astype(np.uint8)).save(path)


def _error_png(err: np.ndarray, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import cm
    from PIL import Image

    e = np.clip(np.nan_to_num(err, nan=1.0, posinf=1.0), 0.0, 1.0)
    Image.fromarray((cm.inferno(e)[..., :3] * 255).astype(np.uint8)).save(path)


def dump_images(tmp_path: Path, name: str, img: np.ndarray, ref: np.ndarray,
                err: np.ndarray) -> Path:
    """Write img, ref (both scaled by ref's max) and err (already in [0, 1] units of the
    tolerance, 1 = at the limit) as PNGs; returns the folder."""
    scale = float(np.nanmax(np.abs(ref))) or 1.0
    _to_png(img, scale, tmp_path / f"{name}_image.png")
    _to_png(ref, scale, tmp_path / f"{name}_reference.png")
    e = err if err.ndim == 2 else err.max(axis=-1)
    _error_png(e, tmp_path / f"{name}_error.png")
    np.save(tmp_path / f"{name}_image.npy", img)
    np.save(tmp_path / f"{name}_reference.npy", ref)
    return tmp_path


def fail_with_images(tmp_path: Path, name: str, img, ref, err, message: str):
    """Write the failure images and raise AssertionError naming where they are."""
    where = dump_images(tmp_path, name, np.asarray(img), np.asarray(ref), np.asarray(err))
    raise AssertionError(f"{message}\n  images: {where}/{name}_{{image,reference,error}}.png")


def assert_image_close(img, ref, tmp_path: Path, name: str, *, rtol: float,
                       atol: float = 0.0, mask=None) -> None:
    """Every pixel (of `mask`, default all) within atol + rtol * |ref|."""
    img, ref = np.asarray(img, np.float64), np.asarray(ref, np.float64)
    assert img.shape == ref.shape, f"{name}: shape {img.shape} != reference {ref.shape}"
    tol = atol + rtol * np.abs(ref)
    err = np.abs(img - ref) / np.where(tol > 0, tol, 1e-300)  # (h, w, 3), 1 = at the limit
    if mask is not None:
        err = np.where(mask[..., None] if mask.ndim == 2 else mask, err, 0.0)
    bad = ~(err <= 1.0)  # NaN counts as bad
    if bad.any():
        worst = tuple(int(i) for i in np.unravel_index(np.nanargmax(np.where(bad, err, -1)),
                                                       err.shape))
        fail_with_images(
            tmp_path, name, img, ref, err,
            f"{name}: {int(bad.any(axis=-1).sum())} of {bad.shape[0] * bad.shape[1]} pixels "
            f"outside atol={atol:g} + rtol={rtol:g}*|ref|; worst at {worst[:2]}: "
            f"{img[worst]:.6g} vs {ref[worst]:.6g}")


__all__ = ["Camera", "Environment", "Instance", "Material", "Mesh", "Scene",
           "RenderSettings", "assert_image_close", "down_camera", "dump_images",
           "fail_with_images", "mesh_from_trimesh", "plane_mesh", "plane_points_seen",
           "render_image", "single", "trs"]
