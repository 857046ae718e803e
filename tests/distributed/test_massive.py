"""The massive demo: deterministic from its seed, and (slow) a scaled-down massive scene
of ~100 MB rendered at K = 4 by a driver that never holds a mesh: the scene is generated
and its metadata computed in another process, and here every mesh read fails."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from nprt.scene.demos import DEMO_SIZES, massive
from nprt.scene.meta import load_scene_meta
from nprt.workers.render import render
from nprt.workers.settings import RenderSettings
from tests.distributed.helpers import refuse_mesh_reads

ROOT = Path(__file__).resolve().parents[2]


def test_massive_is_deterministic_from_its_seed_and_forest_only():
    a, b = (massive.build(3, leaves=300, instances=40) for _ in range(2))
    c = massive.build(4, leaves=300, instances=40)
    assert [m.content_hash for m in a.meshes] == [m.content_hash for m in b.meshes]
    assert np.array_equal(a.instance_transform, b.instance_transform)
    assert [m.content_hash for m in a.meshes] != [m.content_hash for m in c.meshes]
    assert len(a.instances) == 41 and len(a.meshes) == 1 + 4 * massive.VARIANTS
    assert "massive" in DEMO_SIZES["forest"] and "massive" not in DEMO_SIZES["city"]


GENERATE = """
import sys
from nprt.scene.demos import massive
from nprt.scene.io import save_scene
from nprt.scene.meta import load_scene_meta
scene = massive.build(0, leaves=125_000, instances=10_000, name="forest-massive-lite")
path = save_scene(scene, sys.argv[1], instance_file=True)
del scene
load_scene_meta(path)  # the metadata cache, computed here, not by the renderer
"""


@pytest.mark.slow
def test_scaled_down_massive_renders_at_k4_and_the_driver_never_loads_a_mesh(
        ray_local, tmp_path, monkeypatch):
    entry = tmp_path / "lite" / "scene.json"
    entry.parent.mkdir()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    subprocess.run([sys.executable, "-c", GENERATE, str(entry)], check=True, env=env,
                   cwd=ROOT, timeout=600)
    refuse_mesh_reads(monkeypatch)
    meta = load_scene_meta(entry)
    assert meta.mesh_bytes >= 100e6 and len(meta.instances) > 10_000
    s = RenderSettings(width=32, height=24, spp=1, spp_per_pass=1, bounces=2, shards=4)
    result = render(meta, s)
    shard_bytes = result.info["shard_geometry_bytes"]
    assert len(shard_bytes) == 4 and max(shard_bytes) < 0.5 * meta.mesh_bytes
    img = result.film.image()
    assert np.isfinite(img).all() and img.max() > 0
