"""Scenes for nprt: the model, JSON/glTF loading, procedural demos and shard partitioning.

The heavy modules (trimesh, pydantic) load on first use of the names below, so importing
`nprt.scene.model` alone stays cheap.
"""

from importlib import import_module

_EXPORTS = {
    "SceneError": "nprt.scene.errors",
    "Scene": "nprt.scene.model",
    "load_scene": "nprt.scene.json_load",
    "save_scene": "nprt.scene.json_save",
    "load_any": "nprt.scene.io",
    "load_gltf": "nprt.scene.gltf",
    "make_demo": "nprt.scene.demos",
    "DEMOS": "nprt.scene.demos",
    "Partition": "nprt.scene.partition",
}

# `partition` (the function) is not re-exported: `nprt.scene.partition` is its module.
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'scene' has no attribute {name!r}")
