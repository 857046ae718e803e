"""How much ray work each instance brings, estimated from scene metadata alone (the driver
plans placement without geometry).

Two estimates:
- `screen_coverage`: the share of the camera's view each instance's world box covers;
- `pilot_work`, what placement uses: a coarse pilot that casts a grid of camera rays at the
  instances' world boxes (boxes as stand-ins for their geometry). A ray visits the boxes it
  crosses in the order it enters them, and passes each with probability 1 - OPACITY: an
  instance is charged the visits that reach it, and the hits it stops, which it shades and
  whose bounce and shadow rays start in its box. Every instance also gets an equal share of
  one view (bounce rays go anywhere; a scene seen from nowhere falls back to instance
  counts).

The weights were fitted on forest and city at default size, K = 2, 4, 8, to in-process
per-shard CPU (bench_visits), and checked on sculpture and windy (below).
"""

from __future__ import annotations

import numpy as np

from nprt.scene.model import instance_world_bounds

ASPECT = 16 / 9  # the view's width over height: placement does not know the image size
PILOT_RAYS = 4096  # the most camera rays the pilot casts
PILOT_PAIRS = 1_000_000  # the ray-box tests it may make: fewer rays where boxes pile up
MIN_PILOT_RAYS = 256
# Fitted (a grid search) to in-process per-shard CPU of forest and city at K = 2, 4, 8
# under the bytes-only placement (bench_visits.run, 320x180, 8 spp): the per-shard CPU is
# linear in the estimate within 3.2 % of the mean (screen coverage: 6.4 %); on sculpture
# and windy, which the fit did not see, 3.9 % (screen coverage: 8.9 %).
OPACITY = 0.2  # the chance a ray entering an instance's box hits its geometry
HIT_WEIGHT = 2.0  # a hit's shading and the rays it spawns, in units of one visit
BASE_SHARE = 0.5  # every instance's equal share, in views (all the pilot's rays = 1 view)


def _view(scene):
    """(eye, forward, right, up, tan of half the vertical fov), float64."""
    cam = scene.camera
    eye, target, up = (np.asarray(v, np.float64) for v in (cam.eye, cam.target, cam.up))
    fwd = target - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    upv = np.cross(right, fwd)
    return eye, fwd, right, upv, np.tan(np.radians(cam.fov_deg) / 2)


def _screen_rects(scene, boxes: np.ndarray):
    """Each box's projected rectangle in the view, clipped to [-1, 1].

    boxes : (n, 2, 3) float64 world AABBs
    returns lo, hi : (n, 2) float64 (x, y) corners; behind : (n,) bool wholly behind the
    near plane; straddles : (n,) bool some corner before it (its rectangle is a guess)
    """
    eye, fwd, right, upv, half_h = _view(scene)
    corners = np.stack([np.stack([boxes[:, i, 0], boxes[:, j, 1], boxes[:, k, 2]], axis=-1)
                        for i in (0, 1) for j in (0, 1) for k in (0, 1)], axis=1) - eye
    z = corners @ fwd  # (n, 8) depth along the view axis
    near = max(scene.camera.near_distance, 1e-9)
    zc = np.maximum(z, near)
    sx = (corners @ right) / (zc * half_h * ASPECT)
    sy = (corners @ upv) / (zc * half_h)
    lo = np.clip(np.stack([sx.min(1), sy.min(1)], axis=-1), -1.0, 1.0)
    hi = np.clip(np.stack([sx.max(1), sy.max(1)], axis=-1), -1.0, 1.0)
    return lo, hi, z.max(axis=1) < near, z.min(axis=1) < near


def screen_coverage(scene) -> np.ndarray:
    """(n_instances,) float64 in [0, 1]: the fraction of the camera's view that each
    instance's world box covers (its projected bounding rectangle, clipped to the view;
    occlusion ignored). A box reaching behind the near plane is clamped to it."""
    lo, hi, behind, _ = _screen_rects(scene, instance_world_bounds(scene))
    cover = np.prod(np.maximum(hi - lo, 0.0), axis=-1) / 4.0
    cover[behind] = 0.0
    return cover


def pilot_work(scene, opacity: float = OPACITY, hit_weight: float = HIT_WEIGHT,
               base_share: float = BASE_SHARE) -> np.ndarray:
    """(n_instances,) float64 relative ray work, summing to 1 + hit_weight x (the share of
    pilot rays that hit a box) + base_share, in units of the pilot's camera rays.

    Deterministic (a fixed grid, no random numbers). The rays are tested only against the
    boxes whose projected rectangle holds them, so the cost is the rectangles' pixels, kept
    under PILOT_PAIRS by casting fewer rays where boxes pile up.
    """
    if not 0.0 < opacity <= 1.0:
        raise ValueError(f"pilot_work: opacity must be in (0, 1], got {opacity!r}")
    n = len(scene.instances)
    if n == 0:
        return np.zeros(0)
    boxes = instance_world_bounds(scene)  # (n, 2, 3)
    lo, hi, behind, straddles = _screen_rects(scene, boxes)
    lo[straddles], hi[straddles] = -1.0, 1.0  # conservative: test every ray
    cover = np.prod(np.maximum(hi - lo, 0.0), axis=-1) / 4.0
    cover[behind] = 0.0
    n_rays = int(np.clip(PILOT_PAIRS / max(cover.sum(), 1e-12), MIN_PILOT_RAYS, PILOT_RAYS))
    ny = max(int(round(np.sqrt(n_rays / ASPECT))), 1)
    nx = max(int(round(n_rays / ny)), 1)

    # Pixel ranges [x0, x1] x [y0, y1] of the grid cells whose centres each rectangle holds.
    x0 = np.ceil((lo[:, 0] + 1) * nx / 2 - 0.5).astype(np.int64)
    x1 = np.floor((hi[:, 0] + 1) * nx / 2 - 0.5).astype(np.int64)
    y0 = np.ceil((lo[:, 1] + 1) * ny / 2 - 0.5).astype(np.int64)
    y1 = np.floor((hi[:, 1] + 1) * ny / 2 - 0.5).astype(np.int64)
    x0, y0 = np.maximum(x0, 0), np.maximum(y0, 0)
    x1, y1 = np.minimum(x1, nx - 1), np.minimum(y1, ny - 1)
    w, h = np.maximum(x1 - x0 + 1, 0), np.maximum(y1 - y0 + 1, 0)
    w[behind] = 0
    per = w * h  # (n,) candidate rays per box
    box = np.repeat(np.arange(n), per)  # (p,) candidate pairs
    j = np.arange(len(box)) - np.repeat(np.cumsum(per) - per, per)
    px = x0[box] + j % w[box]
    py = y0[box] + j // w[box]

    eye, fwd, right, upv, half_h = _view(scene)
    sx = (px + 0.5) * 2 / nx - 1  # (p,)
    sy = (py + 0.5) * 2 / ny - 1
    d = fwd + (sx * half_h * ASPECT)[:, None] * right + (sy * half_h)[:, None] * upv  # (p, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t0 = (boxes[box, 0] - eye) * inv
        t1 = (boxes[box, 1] - eye) * inv
    # A zero direction component gives inf or nan (0 x inf): a nan slab never limits.
    t_near = np.nanmax(np.where(np.isnan(t0), -np.inf, np.minimum(t0, t1)), axis=1)
    t_far = np.nanmin(np.where(np.isnan(t0), np.inf, np.maximum(t0, t1)), axis=1)
    # Depth from the eye along the view axis, so the near plane is t = near (d . fwd = 1).
    near = max(scene.camera.near_distance, 1e-9)
    enter = np.maximum(t_near, near)
    crossed = t_far >= enter
    box, enter, ray = box[crossed], enter[crossed], (py * nx + px)[crossed]

    # Per ray, the boxes in the order it enters them; a box reached after r others sees the
    # ray with probability (1 - opacity)^r.
    order = np.lexsort((box, enter, ray))
    box, ray = box[order], ray[order]
    first = np.r_[True, ray[1:] != ray[:-1]]
    start = np.maximum.accumulate(np.where(first, np.arange(len(ray)), 0))
    reach = (1.0 - opacity) ** (np.arange(len(ray)) - start)  # (c,) float64
    work = np.bincount(box, weights=reach * (1.0 + hit_weight * opacity), minlength=n)
    return work / (nx * ny) + base_share / n


def instance_work(scene) -> np.ndarray:
    """(n_instances,) float64 relative ray work of each instance: `pilot_work`."""
    return pilot_work(scene)
