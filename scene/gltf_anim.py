"""glTF animation channels on node transforms as frames: each channel's translation,
rotation or scale sampler (LINEAR, STEP; CUBICSPLINE keeps its key values and is
sampled linearly) is sampled at FPS frames per second from time 0 to the last key, and
an instance whose node or any ancestor is animated gets its world transform on every
frame. Only the file's first animation is used; morph-target weights are ignored."""

from __future__ import annotations

import base64
import json
import logging
import struct
from pathlib import Path

import numpy as np
from trimesh.util import unique_name

from nprt.scene.animation import MAX_FRAMES, Animation, sample_linear, sample_rotation, trs_matrices
from nprt.scene.errors import SceneError
from nprt.scene.paths import FileRefs

log = logging.getLogger(__name__)

FPS = 24.0  # frames per second of animation time (glTF keys are in seconds)
_COMPONENTS = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}
_PATHS = {"translation": 3, "rotation": 4, "scale": 3}


def read_gltf_json(path: Path) -> tuple[dict, int | None]:
    """The glTF JSON, and for a GLB the offset of its BIN chunk's data (None for .gltf).
    Reads only the JSON: most files have no animation, and their buffers are big."""
    with open(path, "rb") as fh:
        head = fh.read(20)
        if head[:4] == b"glTF":
            (length,) = struct.unpack_from("<I", head, 12)
            return json.loads(fh.read(length)), 20 + length + 8
        return json.loads(head + fh.read()), None


def read_buffers(path: Path, header: dict, bin_at: int | None, refs: FileRefs,
                 where: str) -> list[bytes]:
    """Every buffer: a GLB's BIN chunk, data URIs, or files beside it (through `refs`)."""
    out = []
    for i, b in enumerate(header.get("buffers", [])):
        uri = b.get("uri")
        if uri is None and i == 0 and bin_at is not None:
            with open(path, "rb") as fh:
                fh.seek(bin_at)
                out.append(fh.read(b.get("byteLength", -1)))
        elif uri is None:
            raise SceneError(f"{where}: buffer {i} has no uri")
        elif uri.startswith("data:"):
            out.append(base64.b64decode(uri.partition(",")[2]))
        else:
            out.append(refs.resolve(uri, "glTF buffer", where).read_bytes())
    return out


def _accessor(header: dict, buffers: list, index: int, where: str) -> np.ndarray:
    """A float accessor as (count, components) float64."""
    try:
        acc = header["accessors"][index]
        if acc["componentType"] != 5126:  # FLOAT
            raise SceneError(f"{where}: accessor {index} is not float (componentType "
                             f"{acc['componentType']}); only float keys are supported")
        width = _COMPONENTS[acc["type"]]
        view = header["bufferViews"][acc["bufferView"]]
        buf = buffers[view["buffer"]]
        start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        stride = view.get("byteStride", 4 * width)
        count = acc["count"]
        raw = np.frombuffer(buf, np.uint8, count=(count - 1) * stride + 4 * width,
                            offset=start) if count else np.zeros(0, np.uint8)
    except (KeyError, IndexError, TypeError, ValueError) as e:
        raise SceneError(f"{where}: accessor {index} cannot be read ({e!r})") from None
    rows = np.lib.stride_tricks.as_strided(raw, (count, 4 * width), (stride, 1)) if count \
        else np.zeros((0, 4 * width), np.uint8)
    return np.ascontiguousarray(rows).view("<f4").astype(np.float64).reshape(count, width)


def _static_trs(node: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """A node's own translation, rotation (w, x, y, z) and scale; None when it has a
    matrix (animated nodes must not, by the glTF spec)."""
    if "matrix" in node:
        return None
    t = np.asarray(node.get("translation", (0, 0, 0)), np.float64)
    x, y, z, w = node.get("rotation", (0, 0, 0, 1))
    s = np.asarray(node.get("scale", (1, 1, 1)), np.float64)
    return t, np.array([w, x, y, z], np.float64), s


def _local_matrix(node: dict) -> np.ndarray:
    if "matrix" in node:
        return np.asarray(node["matrix"], np.float64).reshape(4, 4).T
    t, q, s = _static_trs(node)
    return trs_matrices(t[None], q[None], s[None])[0]


def gltf_animation(path: Path, refs: FileRefs, where: str, node_of_instance: list[tuple]
                   ) -> Animation | None:
    """The file's first animation as frames of its instances, or None without one.
    node_of_instance: per instance, (trimesh frame name, its parent's): the frame is the
    glTF node's unique name, or a per-primitive child of it."""
    header, bin_at = read_gltf_json(path)
    anims = header.get("animations") or []
    if not anims:
        return None
    buffers = read_buffers(path, header, bin_at, refs, where)
    if len(anims) > 1:
        log.warning("%s: %d animations; using the first", where, len(anims))
    anim, nodes = anims[0], header.get("nodes", [])
    tracks: dict[int, dict[str, tuple]] = {}  # node -> path -> (times, values, interp)
    end = 0.0
    for c, ch in enumerate(anim.get("channels", [])):
        w = f"{where}: animations[0].channels[{c}]"
        target = ch.get("target", {})
        node, kind = target.get("node"), target.get("path")
        if kind not in _PATHS:
            log.warning("%s: path %r is not a node transform; ignored", w, kind)
            continue
        if not isinstance(node, int) or not 0 <= node < len(nodes) or "matrix" in nodes[node]:
            raise SceneError(f"{w}: target node {node!r} does not exist or has a matrix")
        sampler = anim["samplers"][ch["sampler"]]
        times = _accessor(header, buffers, sampler["input"], w)[:, 0]
        values = _accessor(header, buffers, sampler["output"], w)
        interp = sampler.get("interpolation", "LINEAR")
        if interp == "CUBICSPLINE":  # (in-tangent, value, out-tangent) per key
            values, interp = values[1::3], "LINEAR"
        if interp not in ("LINEAR", "STEP") or values.shape != (len(times), _PATHS[kind]) \
                or not len(times) or (np.diff(times) <= 0).any() or times[0] < 0:
            raise SceneError(f"{w}: bad sampler ({interp}, {len(times)} key times, values "
                             f"{values.shape}); want increasing times >= 0, one value each")
        if kind == "rotation":
            values = values[:, [3, 0, 1, 2]]  # x, y, z, w -> w, x, y, z
        tracks.setdefault(node, {})[kind] = (times, values, interp.lower())
        end = max(end, float(times[-1]))
    if not tracks:
        return None
    frames = int(np.floor(end * FPS + 1e-6)) + 1
    if frames > MAX_FRAMES:
        raise SceneError(f"{where}: animation lasts {end:g} s, {frames} frames at {FPS:g} "
                         f"fps: more than {MAX_FRAMES}")
    at = np.arange(frames) / FPS
    local: dict[int, np.ndarray] = {}  # animated node -> (N, 4, 4)
    for node, paths in tracks.items():
        t, q, s = _static_trs(nodes[node])
        sampled = {"translation": np.repeat(t[None], frames, 0),
                   "rotation": np.repeat(q[None], frames, 0),
                   "scale": np.repeat(s[None], frames, 0)}
        for kind, (times, values, interp) in paths.items():
            sample = sample_rotation if kind == "rotation" else sample_linear
            sampled[kind] = sample(times, values, at, interp)
        local[node] = trs_matrices(sampled["translation"], sampled["rotation"],
                                   sampled["scale"])
    parent = {c: p for p, n in enumerate(nodes) for c in n.get("children", [])}
    world: dict[int, np.ndarray | None] = {}  # node -> (N, 4, 4), None when it never moves

    def world_of(n: int) -> np.ndarray | None:
        if n not in world:
            up = world_of(parent[n]) if n in parent else None
            if up is None and n not in local:
                world[n] = None
            else:
                up = up if up is not None else _static_world(parent.get(n), parent, nodes)
                mine = local.get(n, _local_matrix(nodes[n]))
                world[n] = np.einsum("fij,fjk->fik", np.broadcast_to(up, (frames, 4, 4)),
                                     np.broadcast_to(mine, (frames, 4, 4)))
        return world[n]

    index = _node_index(nodes)
    moving, xf = [], []
    for i, (name, up) in enumerate(node_of_instance):
        n = index.get(name, index.get(up))
        w = None if n is None else world_of(n)
        if w is not None:
            moving.append(i)
            xf.append(w)
    if not moving:
        return None
    log.info("%s: %d frames at %g fps, %d moving instances", where, frames, FPS, len(moving))
    return Animation(frames, np.array(moving), np.stack(xf, axis=1))


def _static_world(n: int | None, parent: dict, nodes: list) -> np.ndarray:
    m = np.eye(4)
    while n is not None:
        m = _local_matrix(nodes[n]) @ m
        n = parent.get(n)
    return m


def _node_index(nodes: list) -> dict[str, int]:
    """trimesh's unique frame name of each glTF node -> its index (as trimesh names them)."""
    names, counts = {}, {}
    for i, n in enumerate(nodes):
        names[unique_name(n.get("name", str(i)), names, counts=counts)] = i
    return names
