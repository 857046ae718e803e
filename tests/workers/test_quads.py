"""The quad-light and camera-ray kernels (`nprt.workers.kernels.quads`) give the numpy
formulas' bits (tests/workers/oracles.py), dot products through BLAS included."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit

from nprt.scene.demos import make_demo
from nprt.workers.kernels.quads import dot3
from nprt.workers.wavefront.camera import generate_primary
from nprt.workers.wavefront.lights import LightSet
from tests.workers import oracles


@njit
def _dot_rows(a, b):
    out = np.empty(a.shape[0])
    for r in range(a.shape[0]):
        out[r] = dot3(a[r, 0], a[r, 1], a[r, 2], b[0], b[1], b[2])
    return out


@pytest.mark.parametrize("n", [1, 2, 3, 7, 8, 64, 1000, 100_003])
def test_dot3_rounds_like_numpys_float64_matrix_vector_product(n):
    rng = np.random.default_rng(n)
    a = rng.normal(size=(n, 3)) * rng.choice([1e-3, 1.0, 1e3], size=(n, 1))
    b = rng.normal(size=3)
    # Values only: BLAS may turn an exact -0.0 into +0.0.
    assert np.array_equal(_dot_rows(a, b), a @ b)


def _bits(x: np.ndarray) -> np.ndarray:
    return x.view(np.int32 if x.dtype == np.float32 else np.int64)


@pytest.mark.parametrize("name", ["city", "forest", "sculpture"])
def test_quad_lights_and_camera_rays_equal_the_numpy_formulas_bit_for_bit(name):
    scene = make_demo(name, "tiny")
    lights = LightSet(scene)
    assert lights.n_quads > 0
    rng = np.random.default_rng(len(name))
    n = 50_000
    pixel = rng.integers(0, 96 * 64, n).astype(np.uint32)
    sample = rng.integers(0, 64, n).astype(np.uint32)
    o, d = generate_primary(scene.camera, 96, 64, 11, pixel, sample)
    want_o, want_d = oracles.generate_primary(scene.camera, 96, 64, 11, pixel, sample)
    assert np.array_equal(_bits(o), _bits(want_o)) and np.array_equal(_bits(d), _bits(want_d))
    # Camera rays, and rays from around the scene aimed at points on the quads (hits at
    # the edges included).
    q = rng.integers(0, lights.n_quads, n)
    u, v = rng.random((n, 1)), rng.random((n, 1))
    u[: n // 10] = np.round(u[: n // 10])
    aim = lights.quad_corner[q] + u * lights.quad_u[q] + v * lights.quad_v[q]
    p = aim + rng.normal(size=(n, 3)) * 5.0
    to = aim - p
    to = (to / np.linalg.norm(to, axis=1, keepdims=True)).astype(np.float32)
    tmax = np.where(rng.random(n) < 0.5, np.inf, rng.uniform(0.5, 20.0, n)).astype(np.float32)
    hits = 0
    for origin, direction in ((o, d), (p, to)):
        t, light = lights.intersect_quads(origin, direction, tmax)
        want_t, want_light = oracles.intersect_quads(lights, origin, direction, tmax)
        assert np.array_equal(_bits(t), _bits(want_t)) and np.array_equal(light, want_light)
        hits += int((light >= 0).sum())
    assert hits > n // 4
