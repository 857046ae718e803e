"""glTF animation channels on node transforms become frames (generated GLB files)."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
import trimesh
from trimesh.transformations import translation_matrix

from nprt.scene.errors import SceneError
from nprt.scene.gltf import load_gltf
from nprt.scene.gltf_anim import FPS


def _glb(nodes_edit, channels) -> bytes:
    """Two boxes 'still' at x=-2 and 'mover' at x=2 under a node 'rig'; `nodes_edit`
    changes the node list, `channels` are (node name, path, times (k,), values (k, d),
    interpolation) appended as float accessors to the BIN chunk."""
    s = trimesh.Scene()
    box = trimesh.creation.box((1, 1, 1))
    for name, geom, x in (("still", "box", -2), ("mover", "box2", 2)):
        s.add_geometry(box, node_name=name, geom_name=geom, transform=translation_matrix([x, 0, 0]))
    glb = s.export(file_type="glb")
    (jlen,) = struct.unpack_from("<I", glb, 12)
    header = json.loads(glb[20:20 + jlen])
    (blen,) = struct.unpack_from("<I", glb, 20 + jlen)
    blob = bytearray(glb[28 + jlen:28 + jlen + blen])
    nodes_edit(header)
    index = {n.get("name"): i for i, n in enumerate(header["nodes"])}
    anim = {"channels": [], "samplers": []}
    for name, path, times, values, interp in channels:
        acc = []
        for arr, kind in ((np.asarray(times, "<f4"), "SCALAR"), (np.asarray(values, "<f4"),
                                                               {3: "VEC3", 4: "VEC4"})):
            kind = kind if isinstance(kind, str) else kind[arr.shape[1]]
            blob += b"\0" * (-len(blob) % 4)
            header["bufferViews"].append({"buffer": 0, "byteOffset": len(blob),
                                          "byteLength": arr.nbytes})
            blob += arr.tobytes()
            header["accessors"].append({"bufferView": len(header["bufferViews"]) - 1,
                                        "componentType": 5126, "count": len(arr),
                                        "type": kind})
            acc.append(len(header["accessors"]) - 1)
        anim["samplers"].append({"input": acc[0], "output": acc[1], "interpolation": interp})
        anim["channels"].append({"sampler": len(anim["samplers"]) - 1,
                                 "target": {"node": index[name], "path": path}})
    header["animations"] = [anim]
    header["buffers"][0]["byteLength"] = len(blob)
    j = json.dumps(header).encode()
    j += b" " * (-len(j) % 4)
    blob += b"\0" * (-len(blob) % 4)
    body = struct.pack("<I", len(j)) + b"JSON" + j + struct.pack("<I", len(blob)) + b"BIN\0" + blob
    return b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body


def _rig(header):
    """Put 'mover' under a new TRS node 'rig' at the origin."""
    mover = [i for i, n in enumerate(header["nodes"]) if n["name"] == "mover"][0]
    header["nodes"].append({"name": "rig", "children": [mover], "translation": [0, 0, 0]})
    roots = header["scenes"][0]["nodes"]
    roots.remove(mover)
    roots.append(len(header["nodes"]) - 1)


def _positions(scene) -> list[np.ndarray]:
    """(instances, 3) world translations of each frame."""
    return [scene.at_frame(f).instance_transform[:, :3, 3] for f in range(scene.frames)]


def test_a_moving_parent_node_moves_its_child_instance_every_frame(tmp_path):
    path = tmp_path / "anim.glb"
    path.write_bytes(_glb(_rig, [("rig", "translation", [0, 1], [[0, 0, 0], [0, 0, 4]],
                                  "LINEAR")]))
    scene = load_gltf(path)
    assert scene.frames == int(FPS) + 1
    pos = _positions(scene)
    still = [i for i in range(2) if pos[0][i][0] < 0][0]
    mover = 1 - still
    for f, p in enumerate(pos):
        np.testing.assert_allclose(p[still], [-2, 0, 0], atol=1e-6)  # not animated
        np.testing.assert_allclose(p[mover], [2, 0, 4 * f / FPS], atol=1e-6)
    assert scene.at_frame(5).meshes is scene.meshes


def test_step_rotation_on_the_node_itself(tmp_path):
    def trs(header):  # the mover's matrix as TRS, so a channel may target it
        for n in header["nodes"]:
            if n["name"] == "mover":
                del n["matrix"]
                n["translation"] = [2, 0, 0]

    quarter = [0, np.sin(np.pi / 4), 0, np.cos(np.pi / 4)]  # x, y, z, w: 90 deg about y
    path = tmp_path / "step.glb"
    path.write_bytes(_glb(trs, [("mover", "rotation", [0, 0.5], [[0, 0, 0, 1], quarter],
                                 "STEP")]))
    scene = load_gltf(path)
    half = int(0.5 * FPS)
    assert scene.frames == half + 1
    mover = int(np.argmax(scene.instance_transform[:, 0, 3]))
    np.testing.assert_allclose(scene.at_frame(half - 1).instance_transform[mover][:3, :3],
                               np.eye(3), atol=1e-6)
    np.testing.assert_allclose(scene.at_frame(half).instance_transform[mover][:3, :3],
                               [[0, 0, 1], [0, 1, 0], [-1, 0, 0]], atol=1e-6)


def test_a_file_without_animation_has_one_frame(tmp_path):
    path = tmp_path / "still.glb"
    path.write_bytes(_glb(lambda h: None, []))
    (tmp_path / "x.glb").write_bytes(trimesh.creation.box().export(file_type="glb"))
    assert load_gltf(tmp_path / "x.glb").frames == 1 and load_gltf(path).frames == 1


def test_a_channel_on_a_matrix_node_is_refused(tmp_path):
    path = tmp_path / "bad.glb"
    path.write_bytes(_glb(lambda h: None, [("mover", "translation", [0, 1],
                                            [[0, 0, 0], [1, 0, 0]], "LINEAR")]))
    with pytest.raises(SceneError, match=r"channels\[0\]: target node 1 .* has a matrix"):
        load_gltf(path)
