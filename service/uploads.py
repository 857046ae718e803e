"""Turn an uploaded file into a scene directory: sniff the format, extract zips safely.

Zip members are checked before anything is written: absolute paths, `..` parts, drive
letters, backslashes, symlinks, encrypted or exotically compressed members, duplicate
names, a name that is both a file and a directory, and over-long names are refused, and
extracted bytes are counted as written (the sizes in a zip's directory can lie). Every
refusal is a BadUpload (400) naming the member.
"""

from __future__ import annotations

import json
import lzma
import shutil
import stat
import zipfile
import zlib
from pathlib import Path, PurePosixPath

from nprt.service.errors import BadUpload, TooLarge

MAX_ZIP_MEMBERS = 10_000
MAX_NAME_PART_BYTES = 255  # one path component: the limit of common filesystems
MAX_NAME_BYTES = 1024  # a whole member name
SCENE_SUFFIXES = (".json", ".glb", ".gltf")
_CHUNK_BYTES = 1 << 20
_COMPRESSIONS = {zipfile.ZIP_STORED: "stored", zipfile.ZIP_DEFLATED: "deflate",
                 zipfile.ZIP_BZIP2: "bzip2", zipfile.ZIP_LZMA: "lzma"}
# What a damaged member raises while it is read: bad CRC and truncation (BadZipFile,
# EOFError), broken streams (zlib, bz2's OSError, lzma), and zipfile's own refusals.
_READ_ERRORS = (zipfile.BadZipFile, EOFError, zlib.error, lzma.LZMAError, OSError,
                NotImplementedError, RuntimeError, ValueError)


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
        except RecursionError:
            raise BadUpload(f"upload {filename or ''!s} is JSON nested too deeply to read"
                            ) from None
        except ValueError as e:  # JSONDecodeError, UnicodeDecodeError, int digit limits
            raise BadUpload(f"upload {filename or ''!s} looks like JSON but does not parse: {e}"
                            ) from None
        return "gltf" if isinstance(doc, dict) and "asset" in doc else "json"
    raise BadUpload(f"upload {filename or ''!s} is not a GLB, glTF, JSON scene or zip "
                    f"(starts with {head!r})")


def _refuse(name: str, why: str) -> BadUpload:
    return BadUpload(f"zip member {name!r}: {why}")


def safe_member_path(name: str) -> PurePosixPath:
    """The relative path a zip member may be extracted to; BadUpload if it could escape
    or could not be created."""
    if "\\" in name or "\x00" in name:
        raise _refuse(name, "backslashes and NUL bytes are not allowed")
    p = PurePosixPath(name)
    if p.is_absolute() or (p.parts and ":" in p.parts[0]):
        raise _refuse(name, "absolute paths are not allowed")
    if ".." in p.parts:
        raise _refuse(name, "'..' path parts are not allowed")
    if not p.parts:
        raise _refuse(name, "an empty or '.' name is not allowed")
    if len(name.encode("utf-8", "surrogateescape")) > MAX_NAME_BYTES:
        raise _refuse(name[:64] + "...", f"names are limited to {MAX_NAME_BYTES} bytes")
    if any(len(part.encode("utf-8", "surrogateescape")) > MAX_NAME_PART_BYTES
           for part in p.parts):
        raise _refuse(name, f"a path part is over {MAX_NAME_PART_BYTES} bytes")
    return p


def _plan(infos: list[zipfile.ZipInfo]) -> list[tuple[zipfile.ZipInfo, PurePosixPath]]:
    """Check every member before anything is written; (member, relative path) pairs."""
    plan, files, dirs = [], {}, set()
    for info in infos:
        name = info.filename
        rel = safe_member_path(name)
        if stat.S_ISLNK(info.external_attr >> 16):
            raise _refuse(name, "symlinks are not allowed")
        if info.flag_bits & 0x1:
            raise _refuse(name, "encrypted members are not supported")
        if info.compress_type not in _COMPRESSIONS:
            raise _refuse(name, f"compression method {info.compress_type} is not supported "
                                f"({', '.join(_COMPRESSIONS.values())})")
        if info.is_dir():
            if rel in files:
                raise _refuse(name, f"is both a file and a directory ({files[rel]!r})")
            dirs.add(rel)
        else:
            if rel in files:
                raise _refuse(name, f"duplicate name (also {files[rel]!r})")
            if rel in dirs:
                raise _refuse(name, "is both a file and a directory")
            files[rel] = name
        plan.append((info, rel))
    for rel, name in files.items():  # a file "a" and a member "a/b" need "a" as a directory
        clash = next((files[p] for p in rel.parents if p in files), None)
        if clash is not None:
            raise _refuse(name, f"lies under {clash!r}, which is a file")
    return plan


def extract_zip(archive: Path, dest: Path, max_bytes: int) -> list[PurePosixPath]:
    """Extract into `dest` (which must exist and be empty); returns the regular files."""
    try:
        zf = zipfile.ZipFile(archive)
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, OSError, ValueError,
            NotImplementedError) as e:
        raise BadUpload(f"not a readable zip file: {e}") from None
    with zf:
        infos = zf.infolist()
        if len(infos) > MAX_ZIP_MEMBERS:
            raise BadUpload(f"zip holds {len(infos)} members; at most {MAX_ZIP_MEMBERS} allowed")
        plan = _plan(infos)
        root = dest.resolve()
        written = 0
        files = []
        for info, rel in plan:
            target = (dest / rel).resolve()
            if target != root and root not in target.parents:  # belt and braces
                raise _refuse(info.filename, "resolves outside the scene dir")
            if info.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            try:
                with zf.open(info) as src, target.open("xb") as dst:
                    while chunk := src.read(_CHUNK_BYTES):
                        written += len(chunk)
                        if written > max_bytes:
                            raise TooLarge(f"zip extracts to more than {max_bytes} bytes")
                        dst.write(chunk)
            except _READ_ERRORS as e:
                why = e.strerror if isinstance(e, OSError) and e.strerror else str(e)
                raise _refuse(info.filename, f"cannot be extracted: {type(e).__name__}: "
                                             f"{why}") from None
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
