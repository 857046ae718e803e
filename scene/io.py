"""Reading and writing scenes: JSON scene files with PLY/OBJ/GLB meshes, and `load_any`.

Every problem with the input surfaces as one `SceneError` naming the file and the place.
"""

from __future__ import annotations

import json
import logging
import re
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from pydantic import ValidationError

from nprt.scene import schema
from nprt.scene.errors import SceneError
from nprt.scene.instances import read_instance_file, write_instance_file
from nprt.scene.model import (
    INDEX_DTYPE,
    TRANSFORM_DTYPE,
    VERTEX_DTYPE,
    Camera,
    DirectionalLight,
    Environment,
    Instance,
    Instances,
    Material,
    Mesh,
    PointLight,
    QuadLight,
    Scene,
    instance_world_bounds,
    validate_mesh,
    validate_transforms,
)
from nprt.scene.paths import FileRefs, load_trimesh

if TYPE_CHECKING:
    import trimesh

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
MAX_LISTED_ERRORS = 5


# ---------------------------------------------------------------- meshes


def drop_degenerate(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, int]:
    """Remove zero-area triangles (repeated or collinear corners, exactly, in float64).

    vertices : (v, 3) float32
    faces    : (f, 3) uint32
    returns  : (kept faces (g, 3) uint32, number dropped)
    """
    tri = vertices.astype(np.float64)[faces]  # (f, 3, 3)
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (f, 3)
    keep = np.any(cross != 0.0, axis=1)
    return faces[keep], int(len(faces) - keep.sum())


def build_mesh(
    name: str,
    vertices,
    faces,
    normals=None,
    uvs=None,
    material: int = 0,
    where: str | None = None,
) -> Mesh:
    """Validate, cast to the model's dtypes and drop degenerate triangles.

    vertices : (v, 3) float, faces : (f, 3) int, normals : (v, 3) or None, uvs : (v, 2) or None
    """
    where = where or f"mesh {name!r}"
    try:
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces)
        if f.dtype.kind in "fO" and not isinstance(faces, np.ndarray):
            f = np.asarray(faces, dtype=object)  # Python ints past int64 stay exact
    except (ValueError, TypeError) as e:
        raise SceneError(f"{where}: vertices/faces are not numeric arrays: {e}") from None
    v = v.reshape(0, 3) if v.size == 0 else v
    f = _face_indices(f, len(v), where)
    if np.isfinite(v).all() and np.abs(v).max(initial=0.0) > np.finfo(VERTEX_DTYPE).max:
        raise SceneError(f"{where}: vertex coordinates overflow float32")
    n = None if normals is None else np.ascontiguousarray(normals, dtype=VERTEX_DTYPE)
    uv = None if uvs is None else np.ascontiguousarray(uvs, dtype=VERTEX_DTYPE)
    raw = Mesh(name, np.ascontiguousarray(v, dtype=VERTEX_DTYPE), f, n, uv, material)
    validate_mesh(raw, where)
    for label, arr in (("normals", n), ("uvs", uv)):
        if arr is not None and not np.isfinite(arr).all():
            raise SceneError(f"{where}: {label} contain non-finite values")
    kept, dropped = drop_degenerate(raw.vertices, f)
    if len(kept) == 0:
        raise SceneError(f"{where}: all {len(f)} triangles are degenerate (zero area)")
    if dropped:
        log.info("%s: dropped %d degenerate triangles of %d", where, dropped, len(f))
    return Mesh(name, raw.vertices, kept, n, uv, material, dropped)


def _face_indices(f: np.ndarray, n_vertices: int, where: str) -> np.ndarray:
    """f : (f, 3) integers of any dtype (object: Python ints) -> (f, 3) uint32, refusing
    non-integers, negatives and indices past the vertices before a cast could wrap them."""
    if f.size == 0:
        return f.reshape(0, 3).astype(INDEX_DTYPE)
    if f.dtype == object:
        flat = f.ravel().tolist()
        if not all(isinstance(x, int | np.integer) for x in flat):
            raise SceneError(f"{where}: face indices must be integers")
        lo, hi = min(flat), max(flat)
    elif np.issubdtype(f.dtype, np.integer):
        lo, hi = f.min(), f.max()
    else:
        raise SceneError(f"{where}: face indices must be integers, got {f.dtype}")
    if lo < 0:
        raise SceneError(f"{where}: face index {int(lo)} is negative")
    if hi >= n_vertices:
        raise SceneError(f"{where}: face index {int(hi)} out of range for {n_vertices} vertices")
    return np.ascontiguousarray(f.astype(np.int64), dtype=INDEX_DTYPE)


def open_mesh_file(path: Path, where: str,
                   refs: FileRefs | None = None) -> tuple[trimesh.Trimesh, list[Path]]:
    """Read one mesh file through trimesh (multi-mesh files are flattened into one); `path`
    comes from `refs.resolve`, and the files it names (MTL, textures, glTF buffers) are
    read through `refs` too. Returns the mesh and those other files."""
    import trimesh  # here, not at import: a driver planning from metadata never needs it

    refs = refs or FileRefs(path.parent)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise SceneError(f"{where}: unsupported mesh format {path.suffix!r} ({refs.show(path)})")
    loaded, named = load_trimesh(path, refs, f"mesh file {refs.show(path)}", where,
                                 force="scene", process=False)
    meshes = [g for g in loaded.geometry.values() if isinstance(g, trimesh.Trimesh)]
    nodes = loaded.graph.nodes_geometry
    if not meshes:
        raise SceneError(f"{where}: {refs.show(path)} holds no triangle mesh")
    if len(meshes) == 1 and len(nodes) == 1 and np.array_equal(loaded.graph[nodes[0]][0],
                                                                np.eye(4)):
        return meshes[0], named  # as loaded: concatenating would drop the file's normals
    return loaded.to_mesh(), named


def mesh_arrays(tm: trimesh.Trimesh) -> dict:
    """What `build_mesh` takes from a loaded mesh file.

    returns : dict with vertices (v, 3), faces (f, 3), normals (v, 3) or None, uvs (v, 2) or None
    """
    uv = getattr(tm.visual, "uv", None)
    uv = uv if uv is not None and np.shape(uv) == (len(tm.vertices), 2) else None
    normals = _ply_normals(tm) if "_ply_raw" in tm.metadata else file_normals(tm)
    return {"vertices": tm.vertices, "faces": tm.faces, "normals": normals, "uvs": uv}


def read_mesh_file(path: Path, where: str, refs: FileRefs | None = None) -> dict:
    """`mesh_arrays` of `open_mesh_file`."""
    return mesh_arrays(open_mesh_file(path, where, refs)[0])


def file_normals(tm: trimesh.Trimesh) -> np.ndarray | None:
    """Vertex normals the file carried (OBJ `vn`, glTF NORMAL), or None: trimesh keeps
    those in its cache; computed ones are not there until asked for."""
    if "vertex_normals" in tm._cache:
        return np.asarray(tm.vertex_normals)
    return None


def _ply_normals(tm: trimesh.Trimesh) -> np.ndarray | None:
    """The file's own nx/ny/nz as (v, 3) float32, or None. trimesh recomputes normals on
    load; the file's survive in the raw PLY data: a structured array for binary PLY, a
    dict of (v, 1) columns for ASCII PLY."""
    raw = tm.metadata.get("_ply_raw", {}).get("vertex", {}).get("data")
    names = raw.keys() if isinstance(raw, dict) else getattr(getattr(raw, "dtype", None),
                                                             "names", None)
    if not names or not {"nx", "ny", "nz"} <= set(names):
        return None
    normals = np.column_stack([np.ravel(raw[k]) for k in ("nx", "ny", "nz")])  # (v, 3)
    if len(normals) != len(tm.vertices):
        return None
    return normals.astype(VERTEX_DTYPE)


def _write_ply(mesh: Mesh, path: Path) -> None:
    import trimesh
    from trimesh.exchange.ply import export_ply

    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False, validate=False)
    if mesh.normals is not None:
        for i, axis in enumerate("xyz"):
            tm.vertex_attributes["n" + axis] = mesh.normals[:, i].astype(VERTEX_DTYPE)
    if mesh.uvs is not None:
        tm.visual = trimesh.visual.TextureVisuals(uv=mesh.uvs)
    path.write_bytes(export_ply(tm, encoding="binary", vertex_normal=False))


# ---------------------------------------------------------------- textures


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """c : (..., 3) float in [0, 1], sRGB encoded -> linear, same shape, float32."""
    c = np.asarray(c, dtype=np.float32)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def read_texture(path: Path, where: str, refs: FileRefs | None = None) -> np.ndarray:
    """An image (sRGB) or .npy (linear) as texture : (h, w, 3) float32 linear; `path`
    comes from `refs.resolve`."""
    shown = (refs or FileRefs(path.parent)).show(path)
    try:
        if path.suffix.lower() == ".npy":
            tex = np.load(path, allow_pickle=False).astype(np.float32)
        else:
            from PIL import Image

            with Image.open(path) as img:
                tex = srgb_to_linear(np.asarray(img.convert("RGB"), dtype=np.float32) / 255.0)
    except Exception as e:  # PIL/numpy raise many types for bad files
        raise SceneError(f"{where}: could not read texture {shown}: {e}") from None
    if tex.ndim != 3 or tex.shape[2] != 3 or tex.shape[0] == 0 or tex.shape[1] == 0:
        raise SceneError(f"{where}: texture {shown} must have shape (h, w, 3), got {tex.shape}")
    if not np.isfinite(tex).all():
        raise SceneError(f"{where}: texture {shown} has non-finite texels")
    return np.ascontiguousarray(tex)


# ---------------------------------------------------------------- transforms


def trs_matrix(translate=None, rotate_deg=None, scale=None) -> np.ndarray:
    """T @ Rz @ Ry @ Rx @ S as (4, 4) float64; rotate_deg are Euler angles about x, y, z."""
    m = np.eye(4, dtype=TRANSFORM_DTYPE)
    if scale is not None:
        m[:3, :3] = np.diag(np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,)))
    if rotate_deg is not None:
        import trimesh

        r = np.eye(4)
        for axis, deg in zip("xyz", rotate_deg, strict=True):
            r = trimesh.transformations.rotation_matrix(np.radians(deg), _AXES[axis]) @ r
        m = r @ m
    if translate is not None:
        m[:3, 3] = translate
    return m


_AXES = {"x": [1.0, 0.0, 0.0], "y": [0.0, 1.0, 0.0], "z": [0.0, 0.0, 1.0]}


# ---------------------------------------------------------------- scene files


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
    from nprt.scene.animation_io import animate  # deferred: it imports this module

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
        _write_ply(m, path.parent / file)
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
        from nprt.scene.animation_io import animation_doc  # deferred: it imports this module

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


# ---------------------------------------------------------------- convenience


def frame_camera(bounds: np.ndarray, fov_deg: float = 40.0) -> Camera:
    """A camera looking at the box from the front-right, above. bounds : (2, 3) float64."""
    lo, hi = np.asarray(bounds, dtype=np.float64)
    centre = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-6)
    dist = radius / np.sin(np.radians(fov_deg) / 2.0)
    direction = np.array([0.6, 0.45, 1.0]) / np.linalg.norm([0.6, 0.45, 1.0])
    return Camera(tuple((centre + dist * direction).tolist()), tuple(centre.tolist()),
                  (0.0, 1.0, 0.0), fov_deg)


def scene_from_meshes(meshes: list[Mesh], transforms: list[tuple[int, np.ndarray]],
                      materials: tuple[Material, ...], name: str) -> Scene:
    """A scene with a framing camera and a daylight sky, for files without their own."""
    instances = tuple(Instance(mi, xf) for mi, xf in transforms)
    bare = Scene(tuple(meshes), instances, materials, name=name)
    wb = instance_world_bounds(bare)
    bounds = np.stack([wb[:, 0].min(axis=0), wb[:, 1].max(axis=0)])
    sky = Environment(kind="sky", zenith=(0.35, 0.5, 0.9), horizon=(0.9, 0.9, 0.85))
    return Scene(tuple(meshes), instances, materials, environment=sky,
                 camera=frame_camera(bounds), name=name)


def load_any(source, size: str = "default", seed: int = 0, root: Path | None = None) -> Scene:
    """A demo name ("forest", "city:small"), a .json scene, a .glb/.gltf file or a mesh file.
    With `root` set (an upload), no file outside `root` is read."""
    from nprt.scene import demos, gltf  # deferred: both import this module

    if isinstance(source, str) and not source.lower().endswith((".json", *MESH_SUFFIXES)):
        name, _, demo_size = source.partition(":")
        if name in demos.DEMOS:
            return demos.make_demo(name, size=demo_size or size, seed=seed)
    path = Path(source)
    suffix = path.suffix.lower()
    if suffix == ".json":
        return load_scene(path, root)
    if suffix in (".glb", ".gltf"):
        return gltf.load_gltf(path, root)
    if suffix in MESH_SUFFIXES:
        refs = FileRefs(path.parent, root)
        path = refs.resolve(path.name, "mesh file", "")
        where = refs.show(path)
        tm, named = open_mesh_file(path, where, refs)
        mesh = build_mesh(path.stem, where=where, **mesh_arrays(tm))
        material = Material()
        if any(p.suffix.lower() == ".mtl" for p in named):  # an OBJ whose MTL was read
            material = gltf.file_material(tm.visual, path.stem, len(tm.vertices))
        return scene_from_meshes([mesh], [(0, np.eye(4))], (material,), path.stem)
    if not path.exists():
        raise SceneError(
            f"unknown scene {str(source)!r}: not a demo ({', '.join(demos.DEMOS)}) "
            f"and no such file"
        )
    raise SceneError(f"{path}: unsupported scene format {suffix!r} (want .json, .glb, .gltf)")
