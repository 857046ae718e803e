"""Proxy training as parallel Ray tasks: each task loads its own mesh from the scene store
and fills the proxy cache by content hash; per-mesh progress is reported; a task that
fails leaves its mesh traced exactly."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from nprt.proxies.cache import ProxyCache, file_name
from nprt.proxies.config import ProxyConfig
from nprt.proxies.policy import plan_proxies
from nprt.proxies.tasks import RayTrainer
from nprt.scene.io import save_scene
from nprt.scene.meta import load_scene_meta
from nprt.scene.model import Instances, Material, Mesh, Scene
from nprt.scene.partition import partition

pytest.importorskip("torch", reason="training needs PyTorch")

# A few hundred steps on few rays: seconds per proxy, accuracy does not matter here.
QUICK = ProxyConfig(steps=60, n_samples=1 << 13, grid=16,
                    eval_samples=1 << 11, calibrate=False)
WIDTHS = (8,)
# Per instance (sphere, sphere, torus, torus, capsule, capsule): the sphere's work equals the
# other two's, so the work-balanced partition keeps each mesh whole on one of two shards.
WORK = np.array([1.0, 1.0, 0.5, 0.5, 0.5, 0.5])


def _mesh(name: str, tm: trimesh.Trimesh) -> Mesh:
    return Mesh(name, np.asarray(tm.vertices, np.float32), np.asarray(tm.faces, np.uint32))


def _stored_scene(tmp_path):
    """Three meshes, each with instances on both of two shards' sides: every one needs a
    proxy at K = 2. Returns (metadata, the scene file)."""
    meshes = (_mesh("sphere", trimesh.creation.icosphere(subdivisions=3)),
              _mesh("torus", trimesh.creation.torus(1.0, 0.3, major_sections=24,
                                                    minor_sections=24)),
              _mesh("capsule", trimesh.creation.capsule(height=1.0, radius=0.4, count=[24, 24])))
    mesh = np.repeat(np.arange(3), 2)
    xf = np.repeat(np.eye(4)[None], 6, axis=0)
    xf[:, 0, 3] = np.arange(6) * 3.0
    scene = Scene(meshes, Instances(mesh, xf), (Material(),), name="three")
    path = save_scene(scene, tmp_path / "three" / "scene.json", instance_file=True)
    return load_scene_meta(path), path


def test_proxies_train_as_parallel_tasks_and_a_failed_task_falls_back_to_exact(
        ray_local, tmp_path):
    meta, path = _stored_scene(tmp_path)
    assert all(m.nbytes > 5128 for m in meta.meshes)  # heavier than a width-8 proxy
    # The torus changes on disk after planning: its task's load fails the hash check.
    torus_file = path.parent / "scene.mesh001.ply"
    torus_file.write_bytes((path.parent / "scene.mesh002.ply").read_bytes())
    cache = ProxyCache(tmp_path / "proxies", shipped_dir=None)
    seen = []
    trainer = RayTrainer(meta.source, cache.dir, on_progress=seen.append,
                         names={i: m.name for i, m in enumerate(meta.meshes)})
    plan = plan_proxies(meta, partition(meta, 2, work=WORK), target_accuracy=0.5, cache=cache,
                        config=QUICK, widths=WIDTHS, trainer=trainer)
    by_name = {d.name: d for d in plan.decisions}
    assert by_name["sphere"].decision == by_name["capsule"].decision == "proxy"
    torus = by_name["torus"]
    assert torus.decision == "fallback" and "training task failed" in torus.reason
    assert "changed on disk" in torus.reason
    assert set(plan.proxies) == {0, 2}
    for i in (0, 2):  # written to the cache by content hash, by the tasks
        assert (cache.dir / file_name(meta.meshes[i], QUICK.with_width(8))).is_file()
    final = {r["name"]: r for r in seen[-1]}
    assert [final[n]["state"] for n in ("sphere", "torus", "capsule")] == \
        ["done", "failed", "done"]
    assert all(r["seconds"] is not None for r in final.values())
    # Before any task ended, all three were in flight at once.
    assert [r["state"] for r in seen[0]] == ["training"] * 3
    # Trained once: planning again finds them cached and starts no task.
    again = RayTrainer(meta.source, cache.dir)
    plan_proxies(meta, partition(meta, 2, work=WORK), target_accuracy=0.5, cache=cache,
                 config=QUICK, widths=WIDTHS, trainer=again)
    assert [r["mesh"] for r in again.progress] == [1]  # only the failed one is retried
