"""Writing a scene as a JSON scene file, with one binary PLY per mesh, one .npy per texture
and optionally an .npz of instances beside it; what it writes `load_scene` reads back."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from nprt.scene import schema
from nprt.scene.animation_io import animation_doc
from nprt.scene.instances import write_instance_file
from nprt.scene.json_load import validation_error
from nprt.scene.meshfile import write_ply
from nprt.scene.model import Scene


def save_scene(scene: Scene, path, instance_file: bool = False) -> Path:
    """Write `path` (JSON) plus one binary PLY per mesh and one .npy per texture beside it;
    with instance_file, the instances go to `<stem>.instances.npz` (`nprt.scene.instances`).
    An animation is written as keyframes on every frame (`animation_io.animation_doc`), so
    the scene loads back with the same frames; it loads on frame 0."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    stem = path.stem
    mesh_refs = _refs([m.name for m in scene.meshes])
    mat_refs = _refs([m.name for m in scene.materials])
    mats = []
    for i, m in enumerate(scene.materials):
        tex = None
        if m.texture is not None:
            tex = f"{stem}.tex{i:03d}.npy"
            np.save(path.parent / tex, np.asarray(m.texture, dtype=np.float32), allow_pickle=False)
        mats.append({"name": m.name, "albedo": _floats(m.albedo),
                     "emission": _floats(m.emission), "texture": tex})
    meshes = []
    for i, m in enumerate(scene.meshes):
        file = f"{stem}.mesh{i:03d}.ply"
        write_ply(m, path.parent / file)
        meshes.append({"name": m.name, "path": file, "material": mat_refs[m.material]})
    doc = {
        "version": schema.FORMAT_VERSION,
        "name": scene.name,
        "materials": mats,
        "meshes": meshes,
        "instances": {"file": write_instance_file(
            path.parent / f"{stem}.instances.npz", scene.instances).name} if instance_file else [
            {"mesh": mesh_refs[inst.mesh],
             "transform": np.asarray(inst.transform, dtype=np.float64).tolist()}
            for inst in scene.instances
        ],
        "lights": {
            "quads": [_floats_dict(q) for q in scene.quad_lights],
            "points": [_floats_dict(p) for p in scene.point_lights],
            "directionals": [_floats_dict(d) for d in scene.directional_lights],
        },
        "environment": {"kind": scene.environment.kind,
                        **_floats_dict(scene.environment, skip=("kind",))},
        "camera": _floats_dict(scene.camera),
    }
    if scene.animation is not None:
        doc["animation"] = animation_doc(scene)
    try:  # refuse to write a file that load_scene would reject
        spec = schema.SceneFile.model_validate(doc)
    except ValidationError as e:
        raise validation_error(e, f"save_scene({path})") from None
    path.write_text(_compact_json(spec.model_dump(mode="json", exclude_none=True)),
                    encoding="utf-8")
    return path


def _compact_json(doc: dict) -> str:
    # One line per list item: readable, diffable, and thousands of instances stay short.
    def block(value, pad: str) -> str:
        if isinstance(value, list) and value and isinstance(value[0], dict):
            return "[\n" + ",\n".join(pad + "  " + json.dumps(v) for v in value) + "\n" + pad + "]"
        if isinstance(value, dict) and any(isinstance(v, list) for v in value.values()):
            inner = ",\n".join(f"{pad}  {json.dumps(k)}: {block(v, pad + '  ')}"
                               for k, v in value.items())
            return "{\n" + inner + "\n" + pad + "}"
        return json.dumps(value)

    return block(doc, "") + "\n"


def _refs(names: list[str]) -> list:
    # Names are the readable reference; positions stand in when names repeat or are empty.
    unique = len(set(names)) == len(names) and all(names)
    return list(names) if unique else list(range(len(names)))


def _floats(x) -> list | float:
    return np.asarray(x, dtype=np.float64).tolist()


def _floats_dict(obj, skip: tuple[str, ...] = ()) -> dict:
    return {k: _floats(v) for k, v in vars(obj).items() if k not in skip and v is not None}
