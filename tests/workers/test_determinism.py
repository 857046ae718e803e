"""Determinism: the counter-based RNG makes an image a pure function of (scene, settings),
independent of how pixels and samples are batched into passes."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from nprt.scene.model import PointLight, QuadLight
from nprt.workers.render import PassDone, ResumeState, render
from tests.workers.helpers import (
    Camera,
    Environment,
    Instance,
    Material,
    RenderSettings,
    Scene,
    fail_with_images,
    mesh_from_trimesh,
    plane_mesh,
    render_image,
    trs,
)

# Width and height are not multiples of any tile size below, so edge tiles are partial.
BASE = dict(width=40, height=28, spp=6, bounces=4, russian_roulette=True, seed=9)


def _scene():
    torus = mesh_from_trimesh(trimesh.creation.torus(1.0, 0.35, major_sections=24,
                                                     minor_sections=12), "torus", material=1)
    return Scene(
        (plane_mesh(half=6.0, divisions=3), torus),
        (Instance(0, np.eye(4)), Instance(1, trs((0, 0.6, 0), 1.0, (1, 0, 0), 70.0)),
         Instance(1, trs((1.8, 0.4, -1.0), (0.6, 1.0, 0.6), (0, 1, 1), 20.0))),
        materials=(Material(albedo=(0.7, 0.7, 0.7)),
                   Material(albedo=(0.8, 0.3, 0.2), emission=(0.05, 0.0, 0.0))),
        quad_lights=(QuadLight((-1.0, 3.0, -1.0), (2.0, 0.0, 0.0), (0.0, 0.0, 2.0),
                               (3.0, 3.0, 3.0)),),
        point_lights=(PointLight((3.0, 2.0, 2.0), (4.0, 4.0, 4.0)),),
        environment=Environment(kind="sky", zenith=(0.2, 0.3, 0.5), horizon=(0.4, 0.4, 0.4)),
        camera=Camera(eye=(0.0, 3.0, 6.0), target=(0.3, 0.3, 0.0), fov_deg=45.0))


@pytest.fixture(scope="module")
def scene():
    return _scene()


@pytest.fixture(scope="module")
def reference(scene):
    return render_image(scene, **BASE)


def test_same_seed_gives_bit_identical_image(scene, reference):
    again = render_image(scene, **BASE)
    assert np.array_equal(again, reference), (
        f"{int((again != reference).any(axis=-1).sum())} pixels differ between two renders")


def test_different_seed_gives_a_different_image(scene, reference):
    # Guards the test above: the seed must reach the samples, or equality proves nothing.
    other = render_image(scene, **{**BASE, "seed": BASE["seed"] + 1})
    assert (other != reference).any(axis=-1).mean() > 0.5


@pytest.mark.parametrize("tile_size,spp_per_pass", [(8, 1), (16, 4), (24, 5), (64, 6)])
def test_image_does_not_depend_on_tiles_or_samples_per_pass(tmp_path, scene, reference,
                                                            tile_size, spp_per_pass):
    # Changing tiles and sample chunks changes which rays share a batch and the order in
    # which the float64 film sums are added; only that summation order may show.
    img = render_image(scene, **BASE, tile_size=tile_size, spp_per_pass=spp_per_pass)
    err = np.abs(img - reference) / np.maximum(np.abs(reference), 1e-12)
    if not (err <= 1e-6).all():
        fail_with_images(tmp_path, f"batching_{tile_size}_{spp_per_pass}", img, reference,
                         err / 1e-6,
                         f"{int((err > 1e-6).any(axis=-1).sum())} pixels differ by more than "
                         f"1e-6 relative (max {err.max():.3g})")


def test_resumed_render_equals_uninterrupted_render(scene):
    # A render stopped after pass k and resumed from its film sums must give the same
    # image as one that never stopped (the job manager relies on this after a restart).
    settings = RenderSettings(**BASE, tile_size=16, spp_per_pass=2)
    full = render(scene, settings).film.image()
    snapshots = {}

    def keep(done: PassDone):
        snapshots[done.index] = (done.film.sums.copy(), done.film.samples.copy())

    render(scene, settings, on_pass=keep)
    k = len(snapshots) // 2
    sums, samples = snapshots[k]
    resumed = render(scene, settings, resume=ResumeState(k + 1, sums, samples)).film.image()
    assert np.array_equal(resumed, full)


def test_resume_from_passes_finished_out_of_order_equals_uninterrupted_render(scene):
    # A pipelined render finishes passes out of order; its checkpoint holds every pass
    # below next_pass plus a few above it (done). Resuming renders exactly the others.
    from nprt.workers.passes import iter_passes
    from nprt.workers.render import Progress
    from nprt.workers.wavefront.reference import ReferenceRenderer

    settings = RenderSettings(**BASE, tile_size=16, spp_per_pass=2)
    full = render(scene, settings).film.image()
    passes = list(iter_passes(settings))
    k = len(passes) // 2
    held = [p for p in passes if p.index < k or p.index == k + 2]
    renderer = ReferenceRenderer(scene, settings)
    sums = np.zeros((settings.width * settings.height, 3))
    samples = np.zeros(settings.width * settings.height, np.int64)
    for p in held:
        tile, _ = renderer.run_pass(p)
        sums[p.pixels(settings.width)] += tile
        samples[p.pixels(settings.width)] += p.sample1 - p.sample0
    ran = []
    resumed = render(scene, settings, resume=ResumeState(k, sums, samples, done=[k + 2]),
                     on_pass=lambda d: ran.append(d.index))
    assert sorted(ran) == [p.index for p in passes if p.index >= k and p.index != k + 2]
    assert np.array_equal(resumed.film.image(), full)
    progress = Progress(k, [k + 2])
    progress.mark(k)
    progress.mark(k + 1)
    assert (progress.next_pass, progress.done) == (k + 3, set())
