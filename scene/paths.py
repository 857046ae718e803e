"""Where the files a scene names are: one resolver for meshes, textures, MTL files and glTF
buffers and images, optionally confined to a root directory (an upload), so that no
reference can read a file outside it."""

from __future__ import annotations

import errno
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath, PureWindowsPath

from nprt.scene.errors import SceneError, UnsafePath


def file_problem(path: Path) -> str | None:
    """Why `path` cannot be read as a regular file ('not found', 'is a directory', ...), or
    None when it can. Asked before opening: opening a FIFO would block forever."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "is a dangling symlink" if os.path.islink(path) else "not found"
    except PermissionError:
        return "is not readable (permission denied)"
    except OSError as e:
        if e.errno == errno.ELOOP:
            return "is a symlink loop"
        if e.errno == errno.ENOTDIR:
            return "not found (a parent is not a directory)"
        return f"cannot be read ({e.strerror})"
    for test, kind in ((stat.S_ISDIR, "is a directory"), (stat.S_ISFIFO, "is a FIFO"),
                       (stat.S_ISSOCK, "is a socket"), (stat.S_ISCHR, "is a device"),
                       (stat.S_ISBLK, "is a device")):
        if test(mode):
            return f"{kind}, not a regular file"
    return None


@dataclass(frozen=True)
class FileRefs:
    """References resolve against `base` (the directory of the file that names them). With
    `root` set, each must stay inside `root` after resolving symlinks, and messages show
    paths relative to it; without, any local path is read (the CLI)."""

    base: Path
    root: Path | None = None

    def resolve(self, ref: str, what: str, where: str) -> Path:
        """The regular file `ref` names; SceneError (UnsafePath when it leaves `root`)
        naming `what` ("mesh file", "texture") and `where` otherwise."""
        at = f"{where}: " if where else ""
        path = self.base / ref if self.root is None else self._confine(ref, f"{at}{what}")
        problem = file_problem(path)
        if problem is not None:
            raise SceneError(f"{at}{self.show(path)}: {what} {problem}")
        return path

    def _confine(self, ref: str, what: str) -> Path:
        root = self.root.resolve()
        if "\x00" in ref:
            raise UnsafePath(f"{what} path {ref!r} contains a NUL byte")
        if PurePosixPath(ref).is_absolute() or PureWindowsPath(ref).anchor:
            raise UnsafePath(f"{what} path {ref!r} is absolute; paths in an upload must be "
                             f"relative to the file naming them")
        joined = Path(os.path.abspath(self.base / ref))  # `..` folded, symlinks not followed
        if not any(joined.is_relative_to(r) for r in (os.path.abspath(self.root), root)):
            raise UnsafePath(f"{what} path {ref!r} leaves the upload")
        try:
            real = joined.resolve()
        except (OSError, RuntimeError):  # RuntimeError: a symlink loop (Python < 3.13)
            raise SceneError(f"{what} {ref!r} is a symlink loop") from None
        if not real.is_relative_to(root):
            raise UnsafePath(f"{what} path {ref!r} leaves the upload through a symlink")
        return real

    def show(self, path: Path) -> str:
        """How messages name `path`: relative to the root when confined (never a server
        path), as given otherwise."""
        if self.root is None:
            return str(path)
        for root in (self.root.resolve(), Path(os.path.abspath(self.root))):
            if Path(path).is_relative_to(root):
                return Path(path).relative_to(root).as_posix()
        return Path(path).name

    def beside(self, path: Path) -> FileRefs:
        """The references of the file at `path` (an OBJ's MTL, a glTF's buffers)."""
        return FileRefs(Path(path).parent, self.root)


@dataclass
class ReadLog:
    """What a trimesh load asked for: the files read, and the first refusal (trimesh
    swallows errors from some reads, MTL and textures, so `load_trimesh` raises it)."""

    read: list[Path] = field(default_factory=list)
    refused: UnsafePath | None = None


def _resolver_class():
    """TrimeshResolver, defined on first use: importing trimesh costs ~90 MB, which a
    driver that only plans from metadata never pays (nprt.scene.meta)."""
    global _RESOLVER
    if _RESOLVER is not None:
        return _RESOLVER
    import trimesh

    class TrimeshResolver(trimesh.resolvers.Resolver):
        """Hands trimesh the files a mesh file names, through FileRefs."""

        def __init__(self, refs: FileRefs, where: str, file_name: str = "",
                     log: ReadLog | None = None):
            self.refs, self.where, self.file_name = refs, where, file_name
            self.log = log or ReadLog()

        def get(self, name: str) -> bytes:
            try:
                path = self.refs.resolve(name, "referenced file", self.where)
            except UnsafePath as e:
                self.log.refused = self.log.refused or e
                raise
            data = path.read_bytes()
            self.log.read.append(path)
            return data

        def keys(self):
            """Names of the files next to the mesh file (trimesh asks for `name in resolver`)."""
            for folder, _, names in os.walk(self.refs.base):
                for name in names:
                    yield os.path.relpath(os.path.join(folder, name), self.refs.base)

        def write(self, name: str, data) -> None:
            raise SceneError(f"{self.where}: loading a scene never writes files (asked: {name})")

        def namespaced(self, namespace: str):
            return type(self)(FileRefs(self.refs.base / namespace, self.refs.root),
                                   self.where, self.file_name, self.log)

    _RESOLVER = TrimeshResolver
    return _RESOLVER


_RESOLVER = None


def __getattr__(name: str):
    if name == "TrimeshResolver":
        return _resolver_class()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def load_trimesh(path: Path, refs: FileRefs, what: str, where: str,
                 **kwargs) -> tuple[object, list[Path]]:
    """trimesh.load(path, **kwargs) with every file it names read through `refs`; `what`
    names the file in messages ("mesh file rock.obj"). Returns what trimesh loaded and the
    files it read besides `path` (an OBJ's MTL, textures, glTF buffers)."""
    import trimesh

    resolver = _resolver_class()(refs.beside(path), where, Path(path).name)
    try:
        loaded = trimesh.load(path, resolver=resolver, **kwargs)
    except SceneError:  # from the resolver: already names the file and the problem
        raise
    except Exception as e:  # trimesh raises many exception types for bad files
        if resolver.log.refused is not None:
            raise resolver.log.refused from None
        raise SceneError(f"{where}: could not read {what}: {e}") from None
    if resolver.log.refused is not None:
        raise resolver.log.refused
    return loaded, resolver.log.read
