"""Turn an uploaded file into a scene directory: sniff the format, extract zips safely.

Zip members are checked before anything is written: absolute paths, `..` parts, drive
letters, backslashes and symlinks are refused, and extracted bytes are counted as written
(the sizes in a zip's directory can lie).
"""

from __future__ import annotations

import json
import shutil
import stat
import zipfile
from pathlib import Path, PurePosixPath

from service.errors import BadUpload, TooLarge

MAX_ZIP_MEMBERS = 10_000
SCENE_SUFFIXES = (".json", ".glb", ".gltf")
_CHUNK_BYTES = 1 << 20


def sniff(path: Path, filename: str | None) -> str:
    """'glb', 'zip', 'gltf' (JSON glTF) or 'json' (an nprt scene file with inline meshes)."""
    with path.open("rb") as f:
        head = f.read(4)
    if head == b"glTF":
        return "glb"
    if head[:2] == b"PK":
        return "zip"
    if head.lstrip()[:1] == b"{":
        if filename and filename.lower().endswith(".gltf"):
            return "gltf"
        try:
            doc = json.loads(path.read_bytes())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise BadUpload(f"upload {filename or ''!s} looks like JSON but does not parse: {e}"
                            ) from None
        return "gltf" if isinstance(doc, dict) and "asset" in doc else "json"
    raise BadUpload(f"upload {filename or ''!s} is not a GLB, glTF, JSON scene or zip "
                    f"(starts with {head!r})")


def safe_member_path(name: str) -> PurePosixPath:
    """The relative path a zip member may be extracted to; BadUpload if it could escape."""
    if "\\" in name or "\x00" in name:
        raise BadUpload(f"zip member {name!r}: backslashes and NUL bytes are not allowed")
    p = PurePosixPath(name)
    if p.is_absolute() or (p.parts and ":" in p.parts[0]):
        raise BadUpload(f"zip member {name!r}: absolute paths are not allowed")
    if ".." in p.parts:
        raise BadUpload(f"zip member {name!r}: '..' path parts are not allowed")
    return p


def extract_zip(archive: Path, dest: Path, max_bytes: int) -> list[PurePosixPath]:
    """Extract into `dest` (which must exist and be empty); returns the regular files."""
    try:
        zf = zipfile.ZipFile(archive)
    except zipfile.BadZipFile as e:
        raise BadUpload(f"not a readable zip file: {e}") from None
    with zf:
        infos = zf.infolist()
        if len(infos) > MAX_ZIP_MEMBERS:
            raise BadUpload(f"zip holds {len(infos)} members; at most {MAX_ZIP_MEMBERS} allowed")
        plan = []
        for info in infos:  # validate every member before writing any
            rel = safe_member_path(info.filename)
            mode = info.external_attr >> 16
            if stat.S_ISLNK(mode):
                raise BadUpload(f"zip member {info.filename!r}: symlinks are not allowed")
            plan.append((info, rel))
        root = dest.resolve()
        written = 0
        files = []
        for info, rel in plan:
            target = (dest / rel).resolve()
            if target != root and root not in target.parents:  # belt and braces
                raise BadUpload(f"zip member {info.filename!r} resolves outside the scene dir")
            if info.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            with zf.open(info) as src, target.open("xb") as dst:
                while chunk := src.read(_CHUNK_BYTES):
                    written += len(chunk)
                    if written > max_bytes:
                        raise TooLarge(f"zip extracts to more than {max_bytes} bytes")
                    dst.write(chunk)
            files.append(rel)
    return files


def find_entry(files: list[PurePosixPath]) -> PurePosixPath:
    """The scene file in an extracted zip: the shallowest .json, else the shallowest
    .glb/.gltf; it must be unique at its depth."""
    for suffixes in ((".json",), (".glb", ".gltf")):
        found = [f for f in files if f.suffix.lower() in suffixes
                 and not f.name.startswith(".") and "__MACOSX" not in f.parts]
        if not found:
            continue
        depth = min(len(f.parts) for f in found)
        top = sorted(f for f in found if len(f.parts) == depth)
        if len(top) > 1:
            raise BadUpload(f"zip holds several candidate scene files: "
                            f"{', '.join(map(str, top[:5]))}; keep exactly one")
        return top[0]
    listed = ", ".join(map(str, files[:10])) or "nothing"
    raise BadUpload(f"zip holds no scene file ({', '.join(SCENE_SUFFIXES)}); found {listed}")


def unpack(upload: Path, kind: str, dest: Path, max_extract_bytes: int) -> PurePosixPath:
    """Lay out the upload in the empty directory `dest`; returns the entry file, relative."""
    if kind == "zip":
        return find_entry(extract_zip(upload, dest, max_extract_bytes))
    entry = PurePosixPath(f"scene.{kind}")
    shutil.copyfile(upload, dest / entry)
    return entry
