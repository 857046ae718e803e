"""The driver holds no geometry: planning runs on metadata alone (mesh files absent, the
loader made to fail in the driver), each shard loads only its own meshes (and the
replicated ones) from the scene store, and the image still equals the reference."""

from __future__ import annotations

import pytest

from nprt.scene.errors import SceneError
from nprt.scene.meta import load_scene_meta, meta_path
from nprt.scene.store import DirectorySource, open_scene, open_source
from nprt.workers.render import render
from nprt.workers.runtime.placement import plan_placement
from nprt.workers.runtime.pool import ShardPool, pool_key
from tests.distributed.helpers import refuse_mesh_reads, rel_error, settings


@pytest.fixture
def scene_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("NPRT_SCENE_CACHE", str(tmp_path / "scenes"))
    return tmp_path / "scenes"


def test_planning_reads_no_vertex_array(scene_cache, monkeypatch):
    entry = open_scene("forest:small").source.scene_file  # written once, with its cache
    meshes = sorted(p for p in (scene_cache.glob("*/*.ply")))
    assert meshes and meta_path(entry).is_file()
    for p in meshes:
        p.unlink()
    refuse_mesh_reads(monkeypatch)
    meta = load_scene_meta(entry)
    assert meta.summary()["base_meshes"] == len(meshes)
    for mode in ("exact", "oracle"):  # oracle: the proxy policy's replication, no training
        s = settings(3, mode=mode)
        placed = plan_placement(meta, s)
        assert placed.partition.k == 3 and len(placed.owner) == len(meta.instances)
        assert len(pool_key(meta, s)) == 64
        assert bool(placed.plan and placed.plan.replicated) == (mode == "oracle")
    monkeypatch.undo()
    with pytest.raises(SceneError, match="mesh file"):
        meta.source.load_meshes([0])  # the files really are gone


def test_stale_metadata_is_recomputed_and_a_changed_mesh_is_refused(scene_cache):
    meta = open_scene("city:tiny")
    ply = sorted(scene_cache.glob("*/*.ply"))[1]
    other = sorted(scene_cache.glob("*/*.ply"))[2]
    ply.write_bytes(other.read_bytes())
    with pytest.raises(SceneError, match="changed on disk"):
        meta.source.load_meshes([1])  # planned with the old hash
    again = load_scene_meta(meta.source.scene_file)  # size or mtime moved: recomputed
    assert again.meshes[1].content_hash == again.meshes[2].content_hash


def test_each_shard_loads_only_its_meshes(ray_local, scene_cache, monkeypatch):
    # city: 11 meshes, and in proxy mode only the ground and the lightest building are
    # replicated (at `small`, forest replicates every tree but pine).
    meta = open_scene("city:small")
    refuse_mesh_reads(monkeypatch)
    for k, mode in ((2, "exact"), (3, "proxy")):
        s = settings(k, mode=mode)
        pool = ShardPool(meta, s)
        try:
            replicated = pool.plan.replicated if pool.plan is not None else set()
            if mode == "proxy":
                assert replicated, "city's ground is replicated in proxy mode"
            for sid, info in enumerate(pool.shard_info):
                want = set(pool.partition.shard_meshes[sid]) | replicated
                assert info["meshes"] == sorted(want)
                held = sum(meta.meshes[m].nbytes for m in want)
                assert info["geometry_bytes"] == held < meta.mesh_bytes
        finally:
            pool.close()


@pytest.mark.parametrize("k", (2, 4))
def test_render_from_the_store_equals_the_reference(ray_local, scene_cache, references,
                                                    monkeypatch, k):
    meta = open_scene("sculpture:small")
    refuse_mesh_reads(monkeypatch)
    result = render(meta, settings(k))
    assert result.info["shards"] == k
    assert rel_error(result.film.image(), references["sculpture"].film.image()) == 0.0


def test_sources_open_by_url_scheme(scene_cache):
    meta = open_scene("city:tiny")
    for url in (meta.source.url, meta.source.scene_file):
        src = open_source(url)
        assert isinstance(src, DirectorySource) and src.hashes == meta.source.hashes
    assert src.load_meshes([0])[0].content_hash == meta.meshes[0].content_hash
    with pytest.raises(SceneError, match="unknown scheme 's3'"):
        open_source("s3://bucket/scene.json")
