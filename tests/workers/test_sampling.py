"""Statistical checks of the sampling kernels and the counter-based RNG."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from tests.workers import oracles
from tests.workers.oracles import cosine_hemisphere, frame
from tests.workers.rng_rows import uniform

N = 200_000
THETA_BINS, PHI_BINS = 10, 16
NORMALS = {
    "+z": (0.0, 0.0, 1.0),
    "-z": (0.0, 0.0, -1.0),  # the branch point of the Duff et al. frame
    "near -z": (1e-7, 0.0, -1.0),
    "oblique": (0.3, -0.5, 0.8),
}


def _uniforms(source: str):
    if source == "numpy":
        rng = np.random.default_rng(1234)
        return rng.random(N), rng.random(N)
    pixel = np.arange(N, dtype=np.uint32)
    sample = np.zeros(N, np.uint32)
    return uniform(5, pixel, sample, 0, 0), uniform(5, pixel, sample, 0, 1)


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


@pytest.mark.parametrize("normal", list(NORMALS), ids=list(NORMALS))
@pytest.mark.parametrize("source", ["numpy", "counter_rng"])
def test_cosine_hemisphere_matches_cosine_density_chi_square(normal, source):
    n = _unit(NORMALS[normal])
    u1, u2 = _uniforms(source)
    d, pdf = cosine_hemisphere(u1, u2, np.broadcast_to(n, (N, 3)).copy())
    # (theta, phi) in a frame built here, independent of the sampler's own frame.
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t = _unit(np.cross(helper, n))
    s = np.cross(n, t)
    cos_t = np.clip(d @ n, -1.0, 1.0)
    theta = np.arccos(cos_t)
    phi = np.mod(np.arctan2(d @ s, d @ t), 2 * np.pi)
    obs, _, _ = np.histogram2d(theta, phi, bins=[THETA_BINS, PHI_BINS],
                               range=[[0, np.pi / 2], [0, 2 * np.pi]])
    # Integral of cos/pi over a bin: (sin^2 theta_b - sin^2 theta_a) / 2 * dphi / pi.
    edges = np.linspace(0, np.pi / 2, THETA_BINS + 1)
    p_theta = np.diff(np.sin(edges) ** 2)  # sums to 1
    expected = N * np.outer(p_theta, np.full(PHI_BINS, 1.0 / PHI_BINS))
    assert obs.sum() == N, f"{N - obs.sum():.0f} directions fell outside the hemisphere"
    chi2, p = stats.chisquare(obs.ravel(), expected.ravel())
    assert p > 0.01, f"chi-square {chi2:.1f} over {obs.size} bins, p = {p:.2g}"


@pytest.mark.parametrize("normal", list(NORMALS), ids=list(NORMALS))
def test_cosine_hemisphere_returns_unit_directions_and_cos_over_pi_pdf(normal):
    n = _unit(NORMALS[normal])
    u1, u2 = _uniforms("numpy")
    u1[:3] = [0.0, 1.0 - 2**-53, 0.5]  # pole, rim, middle
    d, pdf = cosine_hemisphere(u1, u2, np.broadcast_to(n, (N, 3)).copy())
    assert np.isfinite(d).all() and np.isfinite(pdf).all()
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    cos = d @ n
    assert (cos >= -1e-12).all(), f"{(cos < 0).sum()} directions below the surface"
    np.testing.assert_allclose(pdf, np.maximum(cos, 0.0) / np.pi, atol=1e-12)


def test_frame_is_orthonormal_for_every_normal():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(10_000, 3))
    n = np.concatenate([n, [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, -1, 0], [1e-9, 0, -1]]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t, s = frame(n)
    basis = np.stack([t, s, n], axis=1)  # (k, 3, 3)
    gram = np.einsum("kij,klj->kil", basis, basis)
    np.testing.assert_allclose(gram, np.broadcast_to(np.eye(3), gram.shape), atol=1e-9)


def test_counter_rng_is_uniform_and_independent_across_keys():
    # Kolmogorov-Smirnov per stream, and no correlation between streams that differ in
    # one key (dimension, bounce, sample, seed): images must not show structured noise.
    pixel = np.arange(50_000, dtype=np.uint32)
    zero = np.zeros_like(pixel)
    base = uniform(0, pixel, zero, 0, 0)
    others = {"dim": uniform(0, pixel, zero, 0, 1), "bounce": uniform(0, pixel, zero, 1, 0),
              "sample": uniform(0, pixel, zero + 1, 0, 0), "seed": uniform(1, pixel, zero, 0, 0)}
    for name, x in {"base": base, **others}.items():
        assert ((x >= 0) & (x < 1)).all(), name
        p = stats.kstest(x, "uniform").pvalue
        assert p > 1e-3, f"stream {name}: KS p = {p:.2g}"
    for name, x in others.items():
        r = np.corrcoef(base, x)[0, 1]
        assert abs(r) < 0.02, f"streams differing in {name} correlate: r = {r:.3f}"
    again = uniform(0, pixel, zero, 0, 0)
    assert np.array_equal(base, again), "the RNG is not a pure function of its keys"


def test_compiled_rng_equals_numpy_splitmix_oracle():
    rng = np.random.default_rng(4)
    n = 5000
    pixel = rng.integers(0, 2**32, n, dtype=np.uint64).astype(np.uint32)
    sample = rng.integers(0, 2**32, n, dtype=np.uint64).astype(np.uint32)
    bounce = rng.integers(0, 256, n).astype(np.uint8)
    dim = rng.integers(0, 200, n)
    for seed in (0, 7, (1 << 63) - 1):
        assert np.array_equal(uniform(seed, pixel, sample, bounce, dim),
                              oracles.uniform(seed, pixel, sample, bounce, dim))
        assert np.array_equal(uniform(seed, pixel, sample, 255, 3),
                              oracles.uniform(seed, pixel, sample, 255, 3))
