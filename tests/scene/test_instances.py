"""Instances as arrays: the `.npz` instance file of JSON scenes (round trip, errors that
name the array), the `Instances` model, and setup at scale without one Python object per
instance."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest

import nprt.scene.model as model
from nprt.scene.errors import SceneError
from nprt.scene.instances import read_instance_file, write_instance_file
from nprt.scene.io import load_scene, save_scene
from nprt.scene.model import Instance, Instances, Scene
from nprt.scene.partition import partition
from tests.scene._util import assert_scenes_equal, rich_scene, tetra, translate

TRI = {"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "faces": [[0, 1, 2]]}


def _doc(instances) -> dict:
    return {"meshes": [{"name": "a", **TRI}, {"name": "b", **TRI}], "instances": instances}


def _write(tmp_path, arrays: dict, instances=None) -> object:
    np.savez(tmp_path / "inst.npz", **arrays)
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(_doc(instances or {"file": "inst.npz"})))
    return path


def _load_error(path) -> str:
    with pytest.raises(SceneError) as info:
        load_scene(path)
    assert info.value.__cause__ is None
    return str(info.value)


def _transforms(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xf = np.tile(np.eye(4), (n, 1, 1))
    xf[:, :3, :3] *= rng.uniform(0.5, 2.0, (n, 1, 1))
    xf[:, :3, 3] = rng.normal(size=(n, 3)) * 1e3
    return xf


def test_instance_file_round_trips_bit_for_bit(tmp_path):
    scene = rich_scene()
    path = save_scene(scene, tmp_path / "rich.json", instance_file=True)
    doc = json.loads(path.read_text())
    assert doc["instances"] == {"file": "rich.instances.npz"}
    loaded = load_scene(path)
    assert_scenes_equal(scene, loaded)
    assert loaded.instance_mesh.dtype == np.int32
    assert loaded.instance_transform.dtype == np.float64


def test_instance_file_and_inline_list_load_the_same_scene(tmp_path):
    mesh = np.array([1, 0, 1], np.int64)
    xf = _transforms(3)
    from_file = load_scene(_write(tmp_path, {"mesh": mesh, "transform": xf}))
    listed = [{"mesh": int(m), "transform": t.tolist()} for m, t in zip(mesh, xf, strict=True)]
    (tmp_path / "list.json").write_text(json.dumps(_doc(listed)))
    from_list = load_scene(tmp_path / "list.json")
    assert np.array_equal(from_file.instance_mesh, from_list.instance_mesh)
    assert np.array_equal(from_file.instance_transform, from_list.instance_transform)


@pytest.mark.parametrize("arrays, words", [
    ({"mesh": np.zeros((2, 1), np.int32), "transform": np.tile(np.eye(4), (2, 1, 1))},
     ["'mesh'", "(m,) integer", "(2, 1)"]),
    ({"mesh": np.zeros(2), "transform": np.tile(np.eye(4), (2, 1, 1))},
     ["'mesh'", "integer", "float64"]),
    ({"mesh": np.zeros(2, np.int32), "transform": np.tile(np.eye(4), (3, 1, 1))},
     ["'transform'", "(2, 4, 4)", "(3, 4, 4)"]),
    ({"mesh": np.zeros(2, np.int32), "transform": np.zeros((2, 3, 4))},
     ["'transform'", "(2, 4, 4)", "(2, 3, 4)"]),
    ({"mesh": np.zeros(1, np.int32)}, ["exactly the arrays", "'transform'"]),
    ({"mesh": np.zeros(1, np.int32), "transform": np.eye(4)[None], "colour": np.zeros(1)},
     ["exactly the arrays", "'colour'"]),
    ({"mesh": np.zeros(0, np.int32), "transform": np.zeros((0, 4, 4))}, ["'mesh'", "empty"]),
    ({"mesh": np.array([0, 2], np.int32), "transform": np.tile(np.eye(4), (2, 1, 1))},
     ["'mesh'[1] = 2", "there are 2 meshes"]),
])
def test_bad_instance_file_names_the_array(tmp_path, arrays, words):
    msg = _load_error(_write(tmp_path, arrays))
    assert "instances.file (inst.npz)" in msg, msg
    for w in words:
        assert w in msg, f"{w!r} not in {msg!r}"


def test_bad_transform_in_instance_file_names_its_row(tmp_path):
    xf = np.tile(np.eye(4), (5, 1, 1))
    xf[3, 1, 1] = 0.0  # singular
    msg = _load_error(_write(tmp_path, {"mesh": np.array([0, 1, 0, 1, 0]), "transform": xf}))
    assert "'transform'[3] (mesh 'b')" in msg and "singular" in msg
    xf[3, 1, 1], xf[1, 0, 3] = 1.0, np.nan
    msg = _load_error(_write(tmp_path, {"mesh": np.zeros(5, np.int32), "transform": xf}))
    assert "'transform'[1]" in msg and "non-finite" in msg


def test_missing_or_unreadable_instance_file_is_named(tmp_path):
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(_doc({"file": "nowhere.npz"})))
    assert "instance file not found" in _load_error(path)
    (tmp_path / "junk.npz").write_text("not a zip")
    path.write_text(json.dumps(_doc({"file": "junk.npz"})))
    assert "could not read instance file" in _load_error(path)


def test_instances_field_errors_keep_readable_paths(tmp_path):
    path = tmp_path / "scene.json"
    for instances, where in (({"file": ""}, "instances.file"), ({"fil": "x"}, "instances.fil"),
                             ([{"mesh": "a", "translate": [1, 2]}], "instances[0].translate"),
                             ([], "instances:")):
        path.write_text(json.dumps(_doc(instances)))
        msg = _load_error(path)
        assert where in msg and "array-file" not in msg and "instances.list" not in msg, msg


def test_instances_model_from_list_or_arrays():
    xf = _transforms(3)
    listed = Instances.of([Instance(1, xf[0]), Instance(0, xf[1]), Instance(1, xf[2])])
    arrays = Instances(np.array([1, 0, 1]), xf)
    for inst in (listed, arrays):
        assert inst.mesh.dtype == np.int32 and inst.transform.dtype == np.float64
        assert not inst.mesh.flags.writeable and not inst.transform.flags.writeable
        assert np.array_equal(inst.mesh, [1, 0, 1]) and np.array_equal(inst.transform, xf)
        assert len(inst) == 3 and inst[2].mesh == 1 and np.array_equal(inst[-1].transform, xf[2])
        assert [i.mesh for i in inst] == [1, 0, 1]
    scene = Scene((tetra("a"), tetra("b")), arrays)
    assert scene.instances is arrays and np.array_equal(scene.instances_of_mesh(1), [0, 2])
    copy = pickle.loads(pickle.dumps(scene))
    assert np.array_equal(copy.instance_transform, xf)


def test_instances_model_refuses_bad_shapes():
    with pytest.raises(SceneError, match=r"transform must have shape \(2, 4, 4\)"):
        Instances(np.zeros(2, np.int32), np.zeros((2, 3, 3)))
    with pytest.raises(SceneError, match=r"mesh must be a \(m,\) integer"):
        Instances(np.zeros(2), np.zeros((2, 4, 4)))
    with pytest.raises(SceneError, match=r"instance 1: transform must be 4x4"):
        Instances.of([Instance(0, np.eye(4)), Instance(0, np.eye(3))])
    with pytest.raises(SceneError, match=r"instance 2: mesh 5 does not exist"):
        Scene((tetra(),), Instances(np.array([0, 0, 5]), np.tile(np.eye(4), (3, 1, 1))))
    xf = np.tile(np.eye(4), (3, 1, 1))
    xf[2, 3] = (0, 0, 1, 1)
    with pytest.raises(SceneError, match=r"instance 2 \(mesh 'tetra'\).*not affine"):
        Scene((tetra(),), Instances(np.zeros(3, np.int32), xf))


def test_partition_of_arrays_equals_partition_of_a_list():
    rng = np.random.default_rng(3)
    n = 300
    mesh = rng.integers(0, 3, n)
    xf = np.stack([translate(*rng.uniform(-50, 50, 3)) for _ in range(n)])
    meshes = (tetra("a"), tetra("b"), tetra("c"))
    arrays = Scene(meshes, Instances(mesh, xf))
    listed = Scene(meshes, tuple(Instance(int(m), t) for m, t in zip(mesh, xf, strict=True)))
    for k in (1, 2, 3, 5, 8):
        a, b = partition(arrays, k), partition(listed, k)
        assert np.array_equal(a.instance_shard, b.instance_shard)
        assert a.shard_meshes == b.shard_meshes


def test_many_instances_set_up_without_an_object_per_instance(tmp_path, monkeypatch):
    """20k instances: load, partition, table, BVH and the world's pickle round trip never
    make an `Instance` (a per-instance Python object on the setup path)."""
    from nprt.workers.wavefront.world import ShardWorld

    n = 20_000
    rng = np.random.default_rng(5)
    mesh = rng.integers(0, 2, n).astype(np.int32)
    xf = _transforms(n, seed=5)
    write_instance_file(tmp_path / "many.npz", Instances(mesh, xf))
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(_doc({"file": "many.npz"})))

    class NoInstance(Instance):
        def __init__(self, *a, **kw):
            raise AssertionError("an Instance object was made on the setup path")

    monkeypatch.setattr(model, "Instance", NoInstance)
    scene = load_scene(path)
    part = partition(scene, 3)
    world = pickle.loads(pickle.dumps(ShardWorld.build(scene, part.instance_shard)))
    assert len(world.table) == n and np.array_equal(world.table.mesh, mesh)
    assert world.table.bvh is not None and len(world.table.bvh[-1]) == n
    assert np.bincount(part.instance_shard, minlength=3).min() > 0
    assert read_instance_file(tmp_path / "many.npz", ["a", "b"], "x").transform.shape == (n, 4, 4)
