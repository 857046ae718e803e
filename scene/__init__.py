"""Scenes for nprt: the model, JSON/glTF loading, procedural demos and shard partitioning.

The heavy modules (trimesh, pydantic) load on first use of the names below, so importing
`scene.model` alone stays cheap.
"""

from importlib import import_module

_EXPORTS = {
    "SceneError": "scene.errors",
    "Scene": "scene.model",
    "load_scene": "scene.io",
    "save_scene": "scene.io",
    "load_any": "scene.io",
    "load_gltf": "scene.gltf",
    "make_demo": "scene.demos",
    "DEMOS": "scene.demos",
    "Partition": "scene.partition",
}

# `partition` (the function) is not re-exported: `scene.partition` is its module.
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'scene' has no attribute {name!r}")
