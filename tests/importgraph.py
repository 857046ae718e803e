"""What a module imports when it is imported: module-level import statements read with `ast`
(not those inside functions, which run later, e.g. in a shard actor, nor those under
`if TYPE_CHECKING:`), followed through nprt's own modules. No code is run."""

from __future__ import annotations

import ast
import tomllib
from collections import deque
from pathlib import Path


def package_dirs(root: Path) -> dict[str, Path]:
    """{"nprt.scene": root / "scene", ...} from pyproject.toml's setuptools package-dir."""
    conf = tomllib.loads((root / "pyproject.toml").read_text())
    dirs = conf["tool"]["setuptools"]["package-dir"]
    return {name: root / folder for name, folder in dirs.items()}


class ImportGraph:
    """Module-level imports of every module under the package dirs of a source tree."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self.dirs = package_dirs(self.root)
        self._edges: dict[str, list[str]] = {}

    def file_of(self, module: str) -> Path | None:
        """The .py file that defines `module` (a package's __init__.py), or None when it is
        not one of ours or does not exist."""
        for pkg, folder in self.dirs.items():
            if module == pkg or module.startswith(pkg + "."):
                rel = module[len(pkg):].lstrip(".").split(".") if module != pkg else []
                base = folder.joinpath(*rel)
                for f in (base.with_suffix(".py") if rel else None, base / "__init__.py"):
                    if f is not None and f.is_file():
                        return f
                return None
        return None

    def modules(self) -> list[str]:
        """Every module in the tree, by dotted name."""
        out = []
        for pkg, folder in self.dirs.items():
            for f in sorted(folder.rglob("*.py")):
                parts = list(f.relative_to(folder).with_suffix("").parts)
                if parts[-1] == "__init__":
                    parts.pop()
                out.append(".".join([pkg, *parts]))
        return out

    def imports(self, module: str) -> list[str]:
        """Dotted names `module` imports at import time, parents included (importing a.b.c
        runs a and a.b first). Third-party names are kept whole."""
        if module not in self._edges:
            self._edges[module] = self._read(module)
        return self._edges[module]

    def _read(self, module: str) -> list[str]:
        path = self.file_of(module)
        if path is None:
            return []
        is_pkg = path.name == "__init__.py"
        found: list[str] = []
        for node in _module_level(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                base = _absolute(module, is_pkg, node.module, node.level)
                # `from pkg import sub` imports the submodule sub when there is one
                names = [base] + [f"{base}.{a.name}" for a in node.names
                                  if a.name != "*" and self.file_of(f"{base}.{a.name}")]
            for name in names:
                parts = name.split(".")
                found += [".".join(parts[:i]) for i in range(1, len(parts) + 1)]
        # a module's own parent packages run before it
        parts = module.split(".")
        found += [".".join(parts[:i]) for i in range(1, len(parts))]
        return list(dict.fromkeys(n for n in found if n != module))

    def chains(self, start: str):
        """Yield (name, chain) for every name imported when `start` is imported, with the
        shortest chain of modules start -> ... -> name that imports it (breadth first)."""
        seen = {start: [start]}
        todo = deque([start])
        while todo:
            mod = todo.popleft()
            for name in self.imports(mod):
                if name in seen:
                    continue
                seen[name] = seen[mod] + [name]
                yield name, seen[name]
                if self.file_of(name):
                    todo.append(name)


def _absolute(module: str, is_pkg: bool, name: str | None, level: int) -> str:
    if level == 0:
        return name or ""
    base = module.split(".")
    base = base[:len(base) - level + (1 if is_pkg else 0)]
    return ".".join(base + ([name] if name else []))


def _module_level(tree: ast.Module):
    """Import nodes that run when the module is imported: everywhere except inside function
    bodies and `if TYPE_CHECKING:` blocks (class bodies and try/if blocks do run)."""
    todo = list(tree.body)
    while todo:
        node = todo.pop()
        if isinstance(node, ast.Import | ast.ImportFrom):
            yield node
        elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
            continue
        elif isinstance(node, ast.If) and _is_type_checking(node.test):
            todo.extend(node.orelse)
        else:
            todo.extend(ast.iter_child_nodes(node))


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")
