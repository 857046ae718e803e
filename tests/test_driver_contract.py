"""The driver's static import contract (tests/driver_contract.py) holds for this tree, and
reports a breach added to a copy of it."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from tests.driver_contract import driver_modules, violations
from tests.importgraph import ImportGraph

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("scene", "workers", "proxies", "protos", "service")


def test_no_driver_module_imports_tracing_code_at_import_time():
    assert violations(REPO) == []


def test_the_contract_covers_the_driver_entry_points():
    mods = set(driver_modules(ImportGraph(REPO)))
    assert {"nprt.service.cli", "nprt.service.app", "nprt.service.scheduler",
            "nprt.workers.render", "nprt.workers.frames", "nprt.workers.runtime.coordinator",
            "nprt.workers.runtime.pool", "nprt.workers.stats.counters",
            "nprt.scene.store"} <= mods
    assert not any(m.startswith(("nprt.workers.kernels", "nprt.workers.wavefront.shard"))
                   for m in mods)


@pytest.fixture
def tree(tmp_path) -> Path:
    """A copy of the package sources (python files and pyproject.toml only)."""
    def skip(folder, names):
        return [n for n in names if n == "__pycache__"
                or ((Path(folder) / n).is_file() and not n.endswith(".py"))]

    for pkg in PACKAGES:
        shutil.copytree(REPO / pkg, tmp_path / pkg, ignore=skip)
    shutil.copy(REPO / "pyproject.toml", tmp_path)
    return tmp_path


def _append(path: Path, text: str) -> None:
    path.write_text(path.read_text() + "\n" + text + "\n")


@pytest.mark.parametrize("module, line, reached", [
    ("workers/film.py", "from nprt.workers.kernels.bvh import *", "nprt.workers.kernels"),
    ("workers/runtime/placement.py", "import embreex", "embreex"),
    ("scene/model.py", "import onnxruntime as ort", "onnxruntime"),
    ("service/store.py", "from nprt.workers.traversal import geometry",
     "nprt.workers.traversal"),
    ("workers/stats/counters.py", "try:\n    import numba\nexcept ImportError:\n    pass",
     "numba"),
])
def test_a_module_level_import_of_tracing_code_is_reported(tree, module, line, reached):
    _append(tree / module, line)
    found = violations(tree)
    name = "nprt." + module.removesuffix(".py").replace("/", ".")
    mine = [v for v in found if v.startswith(name + ":")]
    assert len(mine) == 1 and mine[0].endswith(" -> " + reached), found
    # every driver module that imports the broken one is reported too, with its chain
    assert any(f"-> {name} ->" in v for v in found), found


def test_a_breach_through_a_new_module_is_reported_with_its_chain(tree):
    (tree / "workers" / "runtime" / "helper.py").write_text("import trimesh\n")
    _append(tree / "workers" / "runtime" / "raysession.py",
            "from nprt.workers.runtime import helper  # noqa")
    found = violations(tree)
    assert ("nprt.workers.runtime.raysession: nprt.workers.runtime.raysession -> "
            "nprt.workers.runtime.helper -> trimesh") in found, found


def test_an_import_inside_a_function_or_for_type_checking_is_allowed(tree):
    _append(tree / "workers" / "film.py",
            "def _late():\n    import numba\n    return numba\n\n"
            "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import embreex")
    assert violations(tree) == []
