"""Scene metadata: a scene without its vertex arrays. Per base mesh its name, material,
counts, bytes, local bounds and content hash; the instance table, materials, lights and
camera whole. Partitioning, the proxy plan, the pool key and the shards' instance table
need nothing more, so the driver plans a scene of any size from this and each shard loads
its own meshes from the scene store (`nprt.scene.store`).

For a JSON scene the per-mesh part is computed once (each mesh read and checked once, one
at a time) and cached beside it in `<stem>.meta.json`; later opens read no mesh file.
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nprt.scene.errors import SceneError, UnsafePath
from nprt.scene.model import (
    Camera,
    Environment,
    Instances,
    Material,
    Mesh,
    SceneViews,
    validate_scene,
)

log = logging.getLogger(__name__)

META_SUFFIX = ".meta.json"
META_VERSION = 1


@dataclass(frozen=True, eq=False)
class MeshMeta:
    """What planning needs of one base mesh. bounds : (2, 3) float64 local AABB."""

    name: str
    material: int
    n_vertices: int
    n_faces: int
    nbytes: int
    bounds: np.ndarray
    content_hash: str

    @classmethod
    def of(cls, mesh: Mesh) -> MeshMeta:
        return cls(mesh.name, int(mesh.material), len(mesh.vertices), mesh.n_faces,
                   mesh.nbytes, np.asarray(mesh.bounds, np.float64), mesh.content_hash)

    def to_json(self) -> dict:
        return {"name": self.name, "material": self.material, "n_vertices": self.n_vertices,
                "n_faces": self.n_faces, "nbytes": self.nbytes,
                "bounds": self.bounds.tolist(), "content_hash": self.content_hash}

    @classmethod
    def from_json(cls, d: dict) -> MeshMeta:
        bounds = np.array(d["bounds"], np.float64)
        if bounds.shape != (2, 3):
            raise SceneError(f"mesh metadata {d.get('name')!r}: bounds must be (2, 3), "
                             f"got {bounds.shape}")
        return cls(str(d["name"]), int(d["material"]), int(d["n_vertices"]),
                   int(d["n_faces"]), int(d["nbytes"]), bounds, str(d["content_hash"]))


@dataclass(frozen=True, eq=False)
class SceneMeta(SceneViews):
    """A scene without vertex arrays: `Scene`'s fields, with `MeshMeta` for meshes, plus
    `source`, the `nprt.scene.store.MeshSource` its shards load meshes from (None for metadata
    of an in-memory scene, whose meshes the pool puts in Ray's object store). animation:
    as a Scene's (sampled from the scene file's keyframes, which need no mesh); `frames`
    and `at_frame(f)` work as on a Scene."""

    meshes: tuple[MeshMeta, ...]
    instances: Instances
    materials: tuple[Material, ...] = (Material(),)
    quad_lights: tuple = ()
    point_lights: tuple = ()
    directional_lights: tuple = ()
    environment: Environment = field(default_factory=Environment)
    camera: Camera = field(default_factory=Camera)
    name: str = "scene"
    source: object = None
    animation: object | None = None

    def __post_init__(self):
        object.__setattr__(self, "instances", Instances.of(self.instances))
        validate_scene(self, check_meshes=False)
        self._check_animation()

    @classmethod
    def of(cls, scene) -> SceneMeta:
        """The metadata of a `Scene` (or a SceneMeta, returned as is)."""
        if isinstance(scene, SceneMeta):
            return scene
        return cls(tuple(MeshMeta.of(m) for m in scene.meshes), scene.instances,
                   scene.materials, scene.quad_lights, scene.point_lights,
                   scene.directional_lights, scene.environment, scene.camera, scene.name,
                   animation=scene.animation)

    def load(self):
        """The whole `Scene`, meshes included, from `source` (the in-process reference)."""
        if self.source is None:
            raise SceneError(f"scene {self.name!r}: metadata without a mesh source cannot "
                             f"be loaded")
        meshes = self.source.load_meshes(range(len(self.meshes)))
        from nprt.scene.model import Scene

        return Scene(tuple(meshes[i] for i in range(len(self.meshes))), self.instances,
                     self.materials, self.quad_lights, self.point_lights,
                     self.directional_lights, self.environment, self.camera, self.name,
                     self.animation)


def meta_path(scene_file: Path) -> Path:
    scene_file = Path(scene_file)
    return scene_file.with_name(scene_file.stem + META_SUFFIX)


def _file_key(spec_mesh, refs) -> dict:
    """What a cached entry was computed from: the mesh's reference in the scene file, and
    its file's size and mtime when the file is there (an absent file keeps the entry: the
    shard that loads it checks its content hash anyway)."""
    key = {"name": spec_mesh.name, "path": spec_mesh.path,
           "material": spec_mesh.material}
    if spec_mesh.path is None:
        return key
    try:
        st = os.stat(refs.resolve(spec_mesh.path, "mesh file", spec_mesh.name))
        key.update(size=st.st_size, mtime_ns=st.st_mtime_ns)
    except UnsafePath:
        raise  # a planted symlink is refused here too, not waved through from the cache
    except (OSError, SceneError):
        key.update(absent=True)
    return key


def _same(key: dict, cached: dict) -> bool:
    if key.get("absent"):  # compare only what the scene file says
        return all(cached.get(k) == key[k] for k in ("name", "path", "material"))
    return all(cached.get(k) == v for k, v in key.items())


def load_scene_meta(path, root: Path | None = None, write_cache: bool = True) -> SceneMeta:
    """The metadata of a JSON scene file, with a `DirectorySource` for its meshes. Meshes
    whose cached entry is missing or stale are read (one at a time) and the cache is
    rewritten; with the cache current no mesh file is opened."""
    from nprt.scene.json_load import animated, read_spec, scene_parts, spec_mesh
    from nprt.scene.store import DirectorySource

    spec, refs, shown = read_spec(path, root)
    scene_file = refs.resolve(Path(path).name, "scene file", "")
    cache_file = meta_path(scene_file)
    cached = _read_cache(cache_file)
    metas, entries, changed = [], [], False
    try:
        parts = scene_parts(spec, refs)
        for i, ms in enumerate(spec.meshes):
            key = _file_key(ms, refs)
            hit = cached[i] if i < len(cached) else None
            if ms.path is not None and hit is not None and _same(key, hit):
                metas.append(MeshMeta.from_json(hit["meta"]))
                entries.append(hit)
                continue
            meta = MeshMeta.of(spec_mesh(spec, i, refs))  # the mesh is dropped at once
            metas.append(meta)
            entries.append({**key, "meta": meta.to_json()})
            changed = True
    except SceneError as e:
        raise type(e)(f"{shown}: {e}") from None
    changed |= len(cached) != len(entries)
    if changed and write_cache:
        _write_cache(cache_file, entries)
    source = DirectorySource(str(scene_file), None if root is None else str(root),
                             tuple(m.content_hash for m in metas))
    try:
        return animated(SceneMeta(tuple(metas), source=source, **parts), spec)
    except SceneError as e:
        raise type(e)(f"{shown}: {e}") from None


def _read_cache(path: Path) -> list[dict]:
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        return []
    except (OSError, ValueError) as e:
        log.warning("ignoring scene metadata cache %s: %s", path, e)
        return []
    if not isinstance(doc, dict) or doc.get("version") != META_VERSION:
        return []
    meshes = doc.get("meshes")
    return meshes if isinstance(meshes, list) else []


def _write_cache(path: Path, entries: list[dict]) -> None:
    """Atomic; a directory that is not writable only costs recomputing next time."""
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        with os.fdopen(fd, "w") as f:
            json.dump({"version": META_VERSION, "meshes": entries}, f)
        os.replace(tmp, path)
    except OSError as e:
        log.warning("could not write scene metadata cache %s: %s", path, e)
