"""The driver's import contract: what the driver side (the API, scheduler and command line,
the coordinator and pool, statistics, the scene model) may load when it is imported. Read
statically (tests/importgraph.py); `python -m tests.driver_contract` prints the breaches.

The tracing code (numba kernels, Embree, ONNX Runtime) is imported inside the shard actor
(`nprt.workers.runtime.remote.ShardActor.__init__`) and in Ray tasks, never at a driver
module's import time. import-linter is not used: it counts imports inside functions too, and
those are exactly the legitimate ones here. The slow run-time twin, which runs a real
render and reads `sys.modules`, is tests/distributed/test_driver_imports.py."""

from __future__ import annotations

import sys
from fnmatch import fnmatchcase
from pathlib import Path

from tests.importgraph import ImportGraph

# Libraries that trace, compile or train: none may load on the driver at import time.
TRACING_LIBRARIES = ("numba", "llvmlite", "embreex", "onnxruntime", "trimesh", "torch")
# nprt packages that run inside a shard actor or a Ray task.
SHARD_PACKAGES = ("nprt.workers.kernels", "nprt.workers.wavefront", "nprt.workers.traversal",
                  "nprt.workers.routing")

# The driver side, as module-name patterns: workers/ except the shard packages (so the
# top-level API, runtime/ and stats/, and any new sub-package until it is listed above),
# scene/ and service/. proxies/ is not a root: what the driver imports of it is followed.
DRIVER = ("nprt.workers", "nprt.workers.*", "nprt.scene", "nprt.scene.*", "nprt.service",
          "nprt.service.*")
# Scene builders that use trimesh at import: glTF loading and the procedural demos. They run
# when a scene is loaded from glTF or generated, not when a stored scene is rendered, and
# no driver module may import them at module level (the transitive check sees to that).
SCENE_BUILDERS = ("nprt.scene.gltf", "nprt.scene.gltf_anim", "nprt.scene.demos.?*")
# Shard-side modules the driver may import (their own imports are still checked): none
# but the package itself, a docstring.
ALLOWED = ("nprt.workers.wavefront",)


def _matches(name: str, patterns) -> bool:
    return any(fnmatchcase(name, p) for p in patterns)


def driver_modules(graph: ImportGraph) -> list[str]:
    """The modules the contract holds to, by dotted name."""
    return [m for m in graph.modules() if _matches(m, DRIVER)
            and not _matches(m, SHARD_PACKAGES + tuple(p + ".*" for p in SHARD_PACKAGES))
            and not _matches(m, SCENE_BUILDERS)]


def forbidden(name: str) -> bool:
    if name.split(".")[0] in TRACING_LIBRARIES:
        return True
    return name not in ALLOWED and any(name == p or name.startswith(p + ".")
                                       for p in SHARD_PACKAGES)


def violations(root: Path) -> list[str]:
    """One line per driver module that loads a forbidden module at import time, with the
    chain of module-level imports that does it: "a: a -> b -> numba"."""
    graph = ImportGraph(root)
    out = []
    for mod in driver_modules(graph):
        for name, chain in graph.chains(mod):
            if forbidden(name):
                out.append(f"{mod}: {' -> '.join(chain)}")
                break
    return out


if __name__ == "__main__":
    found = violations(Path(__file__).resolve().parents[1])
    print("\n".join(found) or "the driver's import contract holds")
    sys.exit(1 if found else 0)
