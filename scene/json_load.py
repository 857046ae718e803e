"""Reading JSON scene files: parse and validate against `nprt.scene.schema`, then convert to
a `Scene` (or, without reading any mesh, the parts metadata needs). Every problem with the
input surfaces as one `SceneError` naming the file and the place."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from nprt.scene import schema
from nprt.scene.animation_io import animate
from nprt.scene.errors import SceneError
from nprt.scene.instances import read_instance_file
from nprt.scene.meshfile import build_mesh, read_mesh_file
from nprt.scene.model import (
    TRANSFORM_DTYPE,
    Camera,
    DirectionalLight,
    Environment,
    Instances,
    Material,
    Mesh,
    PointLight,
    QuadLight,
    Scene,
    validate_transforms,
)
from nprt.scene.paths import FileRefs
from nprt.scene.texture import read_texture
from nprt.scene.transform import trs_matrix

MAX_LISTED_ERRORS = 5


def load_scene(path, root: Path | None = None) -> Scene:
    """Load a JSON scene file; mesh and texture paths are relative to it, and with `root`
    set (an upload) they must stay inside `root`."""
    spec, refs, shown = read_spec(path, root)
    try:
        return scene_from_spec(spec, refs)
    except SceneError as e:
        raise type(e)(f"{shown}: {e}") from None  # keeps UnsafePath an UnsafePath


def read_spec(path, root: Path | None = None) -> tuple[schema.SceneFile, FileRefs, str]:
    """Parse and validate a JSON scene file without reading any file it names. Returns
    (spec, the resolver for the files it names, the file's name for messages)."""
    refs = FileRefs(Path(path).parent, root)
    path = refs.resolve(Path(path).name, "scene file", "")
    shown = refs.show(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise SceneError(f"{shown}: could not read scene file: {e}") from None
    try:
        data = json.loads(text)
    except RecursionError:
        raise SceneError(f"{shown}: JSON nested too deeply to read (deeper than about "
                         f"{sys.getrecursionlimit()} levels)") from None
    except json.JSONDecodeError as e:
        raise SceneError(
            f"{shown}: malformed JSON at line {e.lineno}, column {e.colno}: {e.msg}"
        ) from None
    try:
        spec = schema.SceneFile.model_validate(data)
    except ValidationError as e:
        raise validation_error(e, shown) from None
    return spec, refs, shown


def validation_error(err: ValidationError, source: str) -> SceneError:
    """One SceneError listing the first few failing JSON field paths."""
    errors = err.errors()
    parts = [f"{_field_path(e['loc'])}: {_message(e)}" for e in errors[:MAX_LISTED_ERRORS]]
    more = len(errors) - MAX_LISTED_ERRORS
    tail = f" (and {more} more errors)" if more > 0 else ""
    return SceneError(f"{source}: invalid scene file: " + "; ".join(parts) + tail)


def _message(e: dict) -> str:
    if e["type"] == "missing" and e["loc"] and isinstance(e["loc"][-1], int):
        return "missing element (too few numbers in this list)"
    return e["msg"].removeprefix("Value error, ")


def _field_path(loc: tuple) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", part) and part not in _UNION_TAGS:
            out += f".{part}" if out else part
        # else: a union-member tag such as 'tuple[float, float, float]', noise for users
    return out or "(top level)"


_UNION_TAGS = {"str", "int", "float", "function-after", "list", "tuple", "none"}


def _resolve(ref, names: list[str], kind: str, field: str) -> int:
    if isinstance(ref, int):
        if ref >= len(names):
            raise SceneError(f"{field}: {kind} index {ref} out of range (there are {len(names)})")
        return ref
    hits = [i for i, n in enumerate(names) if n == ref]
    if not hits:
        raise SceneError(f"{field}: unknown {kind} {ref!r} (known: {', '.join(names[:10])})")
    if len(hits) > 1:
        raise SceneError(f"{field}: {kind} name {ref!r} is ambiguous; refer to it by index")
    return hits[0]


def scene_from_spec(spec: schema.SceneFile, refs: FileRefs | Path) -> Scene:
    """Convert a validated SceneFile; file paths resolve through `refs` (a bare directory:
    relative to it, unconfined)."""
    refs = refs if isinstance(refs, FileRefs) else FileRefs(Path(refs))
    meshes = tuple(spec_mesh(spec, i, refs) for i in range(len(spec.meshes)))
    return animated(Scene(meshes=meshes, **scene_parts(spec, refs)), spec)


def spec_mesh(spec: schema.SceneFile, i: int, refs: FileRefs) -> Mesh:
    """Read and build mesh i of a validated SceneFile (its file, or its inline arrays)."""
    ms = spec.meshes[i]
    where = f"meshes[{i}] ({ms.name!r})"
    mat = 0 if ms.material is None else _resolve(
        ms.material, [m.name for m in spec.materials], "material", f"{where}.material"
    )
    if ms.path is not None:
        arrays = read_mesh_file(refs.resolve(ms.path, "mesh file", where), where, refs)
    else:
        arrays = {"vertices": ms.vertices, "faces": ms.faces,
                  "normals": ms.normals, "uvs": ms.uvs}
    return build_mesh(ms.name, material=mat, where=where, **arrays)


def scene_parts(spec: schema.SceneFile, refs: FileRefs) -> dict:
    """Everything of a scene but its meshes (materials, instances, lights, environment,
    camera, name), as keyword arguments of `Scene`; reads no mesh file."""
    materials = tuple(
        Material(m.name, m.albedo, m.emission, _texture(m.texture, refs, f"materials[{i}] "
                                                        f"({m.name!r})"))
        for i, m in enumerate(spec.materials)
    ) or (Material(),)
    mesh_names = [m.name for m in spec.meshes]
    if isinstance(spec.instances, schema.InstanceFileSpec):  # arrays in an .npz
        instances = read_instance_file(
            refs.resolve(spec.instances.file, "instance file", "instances.file"),
            mesh_names, "instances.file")
    else:
        instances = _listed_instances(spec.instances, mesh_names)
    lights = spec.lights
    return dict(
        instances=instances,
        materials=materials,
        quad_lights=tuple(QuadLight(**q.model_dump()) for q in lights.quads),
        point_lights=tuple(PointLight(**p.model_dump()) for p in lights.points),
        directional_lights=tuple(DirectionalLight(**d.model_dump()) for d in lights.directionals),
        environment=Environment(**spec.environment.model_dump()),
        camera=Camera(**spec.camera.model_dump()),
        name=spec.name,
    )


def animated(scene, spec: schema.SceneFile):
    """`scene` (a Scene or SceneMeta of `spec`) with the spec's animation, on frame 0;
    the keyframes are sampled from the spec alone, so metadata gets them without any mesh."""
    if spec.animation is None:
        return scene
    return animate(scene, spec.animation)


def _texture(ref: str | None, refs: FileRefs, where: str) -> np.ndarray | None:
    return None if ref is None else read_texture(refs.resolve(ref, "texture", where), where, refs)


def _listed_instances(specs: list[schema.InstanceSpec], mesh_names: list[str]) -> Instances:
    """The JSON list form, validated in one vectorised pass (errors name instances[i])."""
    mesh = np.empty(len(specs), np.int64)
    xf = np.empty((len(specs), 4, 4), TRANSFORM_DTYPE)
    resolved: dict = {}  # ref -> mesh index, resolved once per distinct ref
    for i, inst in enumerate(specs):
        key = (type(inst.mesh), inst.mesh)
        if key not in resolved:
            resolved[key] = _resolve(inst.mesh, mesh_names, "mesh", f"instances[{i}].mesh")
        mesh[i] = resolved[key]
        xf[i] = inst.transform if inst.transform is not None else trs_matrix(
            inst.translate, inst.rotate_deg, inst.scale)
    validate_transforms(xf, lambda i: f"instances[{i}] (mesh {mesh_names[mesh[i]]!r})")
    return Instances(mesh, xf)
