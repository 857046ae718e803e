"""The scene store: uploads kept content-addressed (sha256 of the upload) under
<data_dir>/scenes/<id>/, demo scenes by name, and a small cache of loaded scenes."""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import tempfile
import threading
import time
from collections import OrderedDict
from functools import cache
from pathlib import Path

from nprt.scene.errors import SceneError, UnsafePath
from nprt.scene.meta import SceneMeta
from nprt.scene.model import Scene
from nprt.service.config import ServiceSettings
from nprt.service.errors import BadUpload, InvalidScene, NotFound, UnknownScene
from nprt.service.uploads import sniff, unpack

log = logging.getLogger(__name__)

META = "meta.json"
SCENE_ID = re.compile(r"[0-9a-f]{64}")
_SAFE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")


def demo_names() -> tuple[str, ...]:
    from nprt.scene import demos  # deferred: demos build geometry on import in some versions

    return tuple(demos.DEMOS)


def demo_sizes() -> tuple[str, ...]:
    from nprt.scene import demos

    return tuple(demos.SIZES)


def is_demo(ref: str) -> bool:
    """'forest', or 'forest:tiny' with a size the demos know."""
    return ref in _demo_refs()


@cache
def _demo_refs() -> frozenset[str]:
    """Every demo name, alone and with each size (a set: every admission asks)."""
    return frozenset(demo_names()) | {f"{n}:{s}" for n in demo_names() for s in demo_sizes()}


def load_scene_ref(source: str, root: Path | None = None) -> Scene | SceneMeta:
    """Open a demo name or a stored file; with `root`, no file outside it is read. JSON
    scenes and demos come back as metadata with their mesh source (nprt.scene.store): the
    service plans from it and its shards load the meshes, so it holds no geometry."""
    from nprt.scene.store import open_scene

    return open_scene(source, root=root)


class SceneStore:
    def __init__(self, settings: ServiceSettings):
        self.root = settings.scenes_dir
        self.tmp = settings.tmp_dir
        self.max_extract_bytes = settings.max_extracted_bytes
        self.cache_size = settings.scene_cache_size
        self._cache: OrderedDict[str, Scene | SceneMeta] = OrderedDict()
        self._lock = threading.Lock()
        self.root.mkdir(parents=True, exist_ok=True)
        self.tmp.mkdir(parents=True, exist_ok=True)
        demo_names()  # import the demos now, not inside the first request

    # ------------------------------------------------------------ uploads

    def ingest(self, upload: Path, scene_id: str, size_bytes: int,
               filename: str | None) -> tuple[dict, bool]:
        """Unpack, load (to validate) and store an upload whose sha256 is `scene_id`.
        Returns (meta, created); an identical upload returns the stored meta."""
        final = self.root / scene_id
        if (final / META).exists():
            return self.meta(scene_id), False
        kind = sniff(upload, filename)
        work = Path(tempfile.mkdtemp(prefix="scene-", dir=self.tmp))
        try:
            content = work / "content"
            content.mkdir()
            entry = unpack(upload, kind, content, self.max_extract_bytes)
            if kind != "zip":  # the loaders name the scene after the file
                entry = _friendly_entry(content, entry, filename, kind)
            scene = self._validate(content, entry)
            meta = {"id": scene_id, "kind": kind, "filename": filename, "entry": str(entry),
                    "size_bytes": size_bytes, "created_at": time.time(), "summary": scene.summary()}
            (work / META).write_text(json.dumps(meta, indent=1))
            try:
                os.replace(work, final)  # a directory rename: atomic, and never half a scene
            except OSError:
                if (final / META).exists():  # a concurrent identical upload won
                    return self.meta(scene_id), False
                raise
            self._remember(scene_id, scene)
            log.info("stored scene %s (%s, %d bytes, %s)", scene_id, kind, size_bytes,
                     scene.summary())
            return meta, True
        finally:
            shutil.rmtree(work, ignore_errors=True)

    def _validate(self, content: Path, entry) -> Scene | SceneMeta:
        try:
            return load_scene_ref(str(content / entry), root=content)
        except SceneError as e:
            # The client knows its own file names, not our temp directory.
            message = str(e).replace(f"{content}/", "").replace(f"{content.resolve()}/", "")
            raise (BadUpload if isinstance(e, UnsafePath) else InvalidScene)(message) from None
        except Exception as e:  # a loader bug or an exotic file must not become a 500
            log.exception("loading uploaded scene %s failed", entry)
            raise InvalidScene(f"could not load scene {entry}: {type(e).__name__}: {e}") from None

    # ------------------------------------------------------------ lookup

    def meta(self, scene_id: str) -> dict:
        path = self.root / scene_id / META
        if not SCENE_ID.fullmatch(scene_id) or not path.exists():
            raise NotFound(f"no stored scene with id {scene_id!r}")
        return json.loads(path.read_text())

    def uploads(self) -> list[dict]:
        """Stored scenes, newest first."""
        metas = [json.loads(p.read_text()) for p in self.root.glob(f"*/{META}")]
        return sorted(metas, key=lambda m: m["created_at"], reverse=True)

    def describe(self, ref: str) -> dict:
        """Meta of a stored scene, or of a demo (loaded, for its summary)."""
        if SCENE_ID.fullmatch(ref):
            return self.meta(ref)
        if is_demo(ref):
            try:
                scene = self.load(ref)
            except SceneError as e:
                raise NotFound(f"demo scene {ref!r} does not load: {e}") from None
            return {"id": ref, "kind": "demo", "summary": scene.summary()}
        raise NotFound(f"no scene {ref!r}: not a stored scene id nor a demo "
                       f"({', '.join(demo_names())})")

    def check(self, ref: str) -> None:
        """UnknownScene unless a job could name `ref`."""
        if SCENE_ID.fullmatch(ref) and (self.root / ref / META).exists():
            return
        if not is_demo(ref):
            raise UnknownScene(f"unknown scene {ref!r}: not a stored scene id nor a demo name "
                               f"({', '.join(demo_names())}, with an optional size suffix: "
                               f"{', '.join(':' + s for s in demo_sizes())})")

    def source(self, ref: str) -> str:
        """What load_any takes for `ref`: the stored entry file, or the demo name."""
        if SCENE_ID.fullmatch(ref):
            meta = self.meta(ref)
            return str(self.root / ref / "content" / meta["entry"])
        return ref

    def load(self, ref: str) -> Scene | SceneMeta:
        with self._lock:
            if ref in self._cache:
                self._cache.move_to_end(ref)
                return self._cache[ref]
        root = self.root / ref / "content" if SCENE_ID.fullmatch(ref) else None
        scene = load_scene_ref(self.source(ref), root=root)
        self._remember(ref, scene)
        return scene

    def _remember(self, ref: str, scene: Scene | SceneMeta) -> None:
        with self._lock:
            self._cache[ref] = scene
            self._cache.move_to_end(ref)
            while len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)


def _friendly_entry(content: Path, entry, filename: str | None, kind: str):
    """Rename scene.<kind> after the uploaded file name when it is a safe one."""
    name = Path(filename or "").name
    if _SAFE_NAME.fullmatch(name) and name.lower().endswith(f".{kind}"):
        (content / entry).rename(content / name)
        return type(entry)(name)
    return entry
