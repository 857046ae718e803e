"""The distribution installs one top-level package, `nprt`, with everything a render needs;
no source file imports the folders under their bare names."""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("scene", "workers", "proxies", "protos", "service")


def _python_files():
    for folder in (*FOLDERS, "bench", "tests"):
        yield from (ROOT / folder).rglob("*.py")


def test_no_source_imports_a_bare_folder_name():
    bare = []
    for path in _python_files():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module] if isinstance(node, ast.ImportFrom) and node.level == 0
                     else [])
            bare += [f"{path.relative_to(ROOT)}:{node.lineno}: {n}" for n in names
                     if n and n.split(".")[0] in FOLDERS]
    assert not bare, "import these through nprt.*:\n" + "\n".join(bare)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> zipfile.ZipFile:
    """The wheel built offline from a copy of the sources (the checkout stays clean)."""
    src = tmp_path_factory.mktemp("src")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for folder in (*FOLDERS, "bench", "tests"):
        shutil.copytree(ROOT / folder, src / folder,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    out = tmp_path_factory.mktemp("dist")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps",
                    "--no-build-isolation", "--no-index", "-w", str(out), str(src)],
                   check=True, capture_output=True, text=True)
    (path,) = out.glob("nprt-*.whl")
    return zipfile.ZipFile(path)


def test_wheel_has_one_top_level_package(wheel):
    tops = {name.split("/")[0] for name in wheel.namelist()}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"nprt"}, sorted(tops)
    assert not any(n.startswith(("nprt/bench/", "nprt/tests/")) for n in wheel.namelist())


def test_wheel_carries_data_a_render_and_the_service_need(wheel):
    names = set(wheel.namelist())
    shipped = [n for n in names if n.startswith("nprt/proxies/shipped/") and n.endswith(".nprx")]
    assert len(shipped) == len(list((ROOT / "proxies" / "shipped").glob("*.nprx"))) > 0
    static = {str(p.relative_to(ROOT / "service")) for p in (ROOT / "service/static").rglob("*")
              if p.is_file()}
    assert {f"nprt/service/{s}" for s in static} <= names
    assert {"nprt/protos/nprt.proto", "nprt/protos/nprt_pb2.pyi",
            "nprt/service/cli.py"} <= names


def test_installed_package_imports_outside_the_checkout(tmp_path):
    """From another directory only the namespace resolves: nprt.* imports, bare names don't."""
    code = ("import importlib.util as u, nprt.service.cli, nprt.workers.wavefront.shard; "
            f"print([n for n in {FOLDERS!r} if u.find_spec(n) is not None])")
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                       text=True, check=True, env={"PATH": "/usr/bin:/bin"})
    assert r.stdout.strip() == "[]", r.stdout
