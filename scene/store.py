"""The scene store: where shards load their meshes from, so geometry never passes
through the driver. A `MeshSource` is small and picklable; it travels to each shard (and
to each proxy-training task), which loads only the meshes it is told to and checks each
one's content hash against the metadata the driver planned with.

Sources by URL scheme (`open_source`): `file` (a JSON scene on a filesystem every node
can read: a shared filesystem on a real cluster) is `DirectorySource`; `ray` is
`ObjectStoreSource`, meshes of an in-memory scene put once in Ray's object store. Another
location (an object store such as S3, an HTTP server) is one more `MeshSource` subclass
registered in `SCHEMES`.
"""

from __future__ import annotations

import abc
import hashlib
import logging
import os
import re
import shutil
import tempfile
from collections.abc import Iterable
from pathlib import Path
from urllib.parse import urlparse

from nprt.scene.errors import SceneError
from nprt.scene.model import Mesh

log = logging.getLogger(__name__)

DEFAULT_CACHE = "~/.cache/nprt/scenes"


def scene_cache_dir() -> Path:
    """Where demo scenes are written once and read by every shard: $NPRT_SCENE_CACHE, or
    ~/.cache/nprt/scenes. On a cluster it must be a filesystem every node mounts."""
    return Path(os.environ.get("NPRT_SCENE_CACHE", DEFAULT_CACHE)).expanduser()


class MeshSource(abc.ABC):
    """hashes: (n_meshes,) content hash of each mesh, as planned; a loaded mesh that does
    not match fails loudly instead of rendering other geometry than was planned."""

    url: str
    hashes: tuple[str, ...]

    @abc.abstractmethod
    def _load(self, indices: list[int]) -> dict[int, Mesh]:
        """The meshes `indices`, unchecked."""

    def load_meshes(self, indices: Iterable[int]) -> dict[int, Mesh]:
        """{mesh index: Mesh} for `indices`, each checked against its planned hash."""
        indices = sorted({int(i) for i in indices})
        bad = [i for i in indices if not 0 <= i < len(self.hashes)]
        if bad:
            raise SceneError(f"{self.url}: no mesh {bad[0]} (the scene has {len(self.hashes)})")
        meshes = self._load(indices)
        for i in indices:
            got, want = meshes[i].content_hash, self.hashes[i]
            if got != want:
                raise SceneError(f"{self.url}: mesh {i} ({meshes[i].name!r}) has content hash "
                                 f"{got[:12]}, not {want[:12]} as when the scene was planned; "
                                 f"it changed on disk")
        return meshes

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.url!r}, {len(self.hashes)} meshes)"


class DirectorySource(MeshSource):
    """Meshes of a JSON scene file, read where the source is used. root: with it set (an
    upload), no file outside it is read, as when the scene was first loaded."""

    def __init__(self, scene_file: str, root: str | None, hashes: tuple[str, ...]):
        self.scene_file, self.root, self.hashes = str(scene_file), root, tuple(hashes)
        self.url = Path(self.scene_file).resolve().as_uri()

    def _load(self, indices: list[int]) -> dict[int, Mesh]:
        from nprt.scene.json_load import read_spec, spec_mesh

        spec, refs, shown = read_spec(self.scene_file, None if self.root is None
                                      else Path(self.root))
        if len(spec.meshes) != len(self.hashes):
            raise SceneError(f"{shown}: has {len(spec.meshes)} meshes, not "
                             f"{len(self.hashes)} as when the scene was planned")
        try:
            return {i: spec_mesh(spec, i, refs) for i in indices}
        except SceneError as e:
            raise type(e)(f"{shown}: {e}") from None


class ObjectStoreSource(MeshSource):
    """Meshes of an in-memory scene, each put once in Ray's object store; a shard gets
    only the ones it holds. refs : one ObjectRef per mesh."""

    def __init__(self, refs: list, hashes: tuple[str, ...]):
        self.refs, self.hashes = list(refs), tuple(hashes)
        self.url = f"ray://objects/{len(self.refs)}-meshes"

    @classmethod
    def put(cls, meshes) -> ObjectStoreSource:
        import ray

        return cls([ray.put(m) for m in meshes], tuple(m.content_hash for m in meshes))

    def _load(self, indices: list[int]) -> dict[int, Mesh]:
        import ray

        return dict(zip(indices, ray.get([self.refs[i] for i in indices]), strict=True))


def _file_source(url: str) -> DirectorySource:
    from nprt.scene.meta import load_scene_meta

    return load_scene_meta(urlparse(url).path if "://" in url else url).source


SCHEMES = {"file": _file_source, "": _file_source}


def open_source(url: str) -> MeshSource:
    """The MeshSource of a scene location (`file:///data/scene.json` or a plain path)."""
    scheme = urlparse(str(url)).scheme if "://" in str(url) else ""
    if scheme not in SCHEMES:
        raise SceneError(f"scene store {url!r}: unknown scheme {scheme!r}; known: "
                         f"{', '.join(s for s in SCHEMES if s)}")
    return SCHEMES[scheme](str(url))


# ------------------------------------------------------------------ scenes by name


def _demo_version() -> str:
    """Digest of the demo generators' source (the package's registry aside): editing one
    invalidates the cached files."""
    from nprt.scene import demos

    h = hashlib.sha256()
    for p in sorted(Path(demos.__file__).parent.glob("*.py")):
        if p.name != "__init__.py":
            h.update(p.read_bytes())
    return h.hexdigest()[:12]


_DEMO_DIR = re.compile(r"(?P<name>[a-z]+)-(?P<size>[a-z]+)-s\d+-(?P<version>[0-9a-f]{12})")


def demo_dir(name: str, size: str, seed: int = 0) -> Path:
    return scene_cache_dir() / f"{name}-{size}-s{int(seed)}-{_demo_version()}"


def materialize_demo(name: str, size: str = "default", seed: int = 0) -> Path:
    """The demo's JSON scene file in the scene cache, generated and written once (to a
    temporary directory, then renamed: never half a scene), with its metadata cache."""
    from nprt.scene.demos import build_demo
    from nprt.scene.meta import load_scene_meta

    final = demo_dir(name, size, seed)
    entry = final / "scene.json"
    if entry.exists():
        return entry
    final.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{final.name}-", dir=final.parent))
    try:
        build_demo(name, size, seed, work / "scene.json")
        load_scene_meta(work / "scene.json")  # the metadata cache, computed here once
        try:
            os.replace(work, final)
        except OSError:
            if not entry.exists():  # else a concurrent writer won
                raise
    finally:
        shutil.rmtree(work, ignore_errors=True)
    log.info("demo %s:%s (seed %d) written to %s", name, size, seed, final)
    stale = stale_demos()
    if stale:
        log.warning("the scene cache %s holds %d demos of older nprt versions (%.1f GB); "
                    "`nprt scenes --prune` deletes them", final.parent, len(stale),
                    sum(b for _, b in stale) / 1e9)
    return entry


def stale_demos() -> list[tuple[Path, int]]:
    """(directory, bytes) of every demo in the scene cache written by other versions of
    the demo generators: this version never reads them again. Directories being written
    (dot-prefixed) do not match."""
    from nprt.scene.demos import DEMOS

    root, current = scene_cache_dir(), _demo_version()
    if not root.is_dir():
        return []
    out = []
    for d in sorted(root.iterdir()):
        m = _DEMO_DIR.fullmatch(d.name)  # demo_dir's names only: nothing else is touched
        if m and m["name"] in DEMOS and m["version"] != current and d.is_dir():
            out.append((d, sum(f.stat().st_size for f in d.rglob("*") if f.is_file())))
    return out


def prune_demos() -> list[tuple[Path, int]]:
    """Delete `stale_demos()`; returns what was deleted. Never automatic: on a cluster a
    node still running an older nprt may be reading them from the shared cache."""
    gone = stale_demos()
    for d, _ in gone:
        shutil.rmtree(d)
        log.info("pruned stale demo %s", d)
    return gone


def open_scene(source, size: str = "default", seed: int = 0, root: Path | None = None):
    """A scene for distributed rendering: metadata with a `MeshSource` where the scene is
    stored as files (JSON scenes, and demos, written once to the scene cache), so the
    caller holds no vertex array; a glTF or single mesh file is loaded whole (a `Scene`)."""
    from nprt.scene import demos
    from nprt.scene.io import MESH_SUFFIXES, load_any
    from nprt.scene.meta import load_scene_meta

    text = str(source)
    if not text.lower().endswith((".json", *MESH_SUFFIXES)):
        name, _, demo_size = text.partition(":")
        if name in demos.DEMOS:
            demos.check_demo(name, demo_size or size)
            return load_scene_meta(materialize_demo(name, demo_size or size, seed))
    if text.lower().endswith(".json"):
        return load_scene_meta(source, root)
    return load_any(source, size=size, seed=seed, root=root)
