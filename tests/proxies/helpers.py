"""Analytic meshes and a torch-free stand-in proxy for the proxy tests."""

from __future__ import annotations

import numpy as np
import onnx
import trimesh
from onnx import TensorProto, helper

from nprt.proxies.inference import NETS, Proxy
from nprt.proxies.sampling import proxy_box
from nprt.scene.model import Mesh


def from_trimesh(name: str, tm: trimesh.Trimesh) -> Mesh:
    return Mesh(name, np.asarray(tm.vertices, np.float32), np.asarray(tm.faces, np.uint32))


def sphere() -> Mesh:
    return from_trimesh("sphere", trimesh.creation.icosphere(subdivisions=3))


def box() -> Mesh:
    return from_trimesh("box", trimesh.creation.box(extents=(1.0, 0.6, 0.8)))


def torus(major_sections: int = 32, minor_sections: int = 32) -> Mesh:
    return from_trimesh("torus", trimesh.creation.torus(
        major_radius=1.0, minor_radius=0.3, major_sections=major_sections,
        minor_sections=minor_sections))


def triangle() -> Mesh:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    return Mesh("triangle", v, np.array([[0, 1, 2]], np.uint32))


def _mean_model(n_in: int, scale: float) -> bytes:
    """ONNX y = scale * mean(x, axis=1): a fixed function of the encoded input, no torch."""
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, ["n", n_in])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, ["n"])
    axes = helper.make_tensor("axes", TensorProto.INT64, [1], [1])
    s = helper.make_tensor("s", TensorProto.FLOAT, [], [scale])
    nodes = [helper.make_node("ReduceMean", ["x", "axes"], ["m"], keepdims=0),
             helper.make_node("Mul", ["m", "s"], ["y"])]
    graph = helper.make_graph(nodes, "mean", [x], [y], initializer=[axes, s])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 8
    return model.SerializeToString()


def stand_in_proxy(mesh: Mesh, config, accuracy: float = 0.5,
                   eval_rays: int | None = None) -> Proxy:
    """A Proxy in the real container, keyed like a trained one, with fixed ONNX nets; its
    report gives `accuracy` held-out (over `eval_rays` rays where given)."""
    box_ = proxy_box(mesh.bounds)
    meta = {
        "content_hash": mesh.content_hash, "mesh_name": mesh.name, "width": config.width,
        "blocks": config.blocks, "encoding": "paper", "bounds": mesh.bounds.tolist(),
        "box": box_.tolist(), "diag": float(np.linalg.norm(box_[1] - box_[0])),
        "threshold": 0.5, "config": config.to_dict(), "config_key": config.key,
        "report": {"accuracy": accuracy,
                   **({} if eval_rays is None else {"eval_rays": eval_rays})},
    }
    models = {k: _mean_model(5, s) for k, s in zip(NETS, (1.0, 0.5), strict=True)}
    onnx.checker.check_model(onnx.load_from_string(models["depth"]))
    return Proxy(meta, models)


def scene_of(*meshes: Mesh, copies: int = 1):
    """A scene with `copies` instances of every mesh, spread along x."""
    from nprt.scene.model import Instance, Scene

    insts = []
    for i, _ in enumerate(meshes):
        for c in range(copies):
            t = np.eye(4)
            t[0, 3] = 4.0 * (i * copies + c)
            insts.append(Instance(i, t))
    return Scene(tuple(meshes), tuple(insts), name="proxy-test")


def constant_net(value: float, n_in: int) -> bytes:
    """ONNX x (n, n_in) -> y (n, 1) = value, through a real MatMul so the batch axis flows."""
    from onnx import numpy_helper

    zeros = numpy_helper.from_array(np.zeros((n_in, 1), np.float32), "w")
    const = numpy_helper.from_array(np.array([value], np.float32), "c")
    graph = helper.make_graph(
        [helper.make_node("MatMul", ["x", "w"], ["z"]), helper.make_node("Add", ["z", "c"], ["y"])],
        "constant", [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["n", n_in])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["n", 1])], [zeros, const])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    return model.SerializeToString()


def lying_proxy(mesh: Mesh, config, visibility: float = 1.0) -> Proxy:
    """A proxy wrong on purpose: one visibility everywhere (1: "occluded" through any box),
    whose report claims a perfect held-out error curve, so the accuracy target trusts it."""
    from nprt.proxies.encoding import N_INPUTS
    from nprt.proxies.evaluate import CURVE_BANDS

    box_ = proxy_box(mesh.bounds)
    zeros = [0.0] * len(CURVE_BANDS)
    meta = {
        "content_hash": mesh.content_hash, "mesh_name": mesh.name, "width": config.width,
        "blocks": config.blocks, "encoding": "line", "bounds": mesh.bounds.tolist(),
        "box": box_.tolist(), "diag": float(np.linalg.norm(box_[1] - box_[0])),
        "threshold": 0.5, "config": config.to_dict(), "config_key": config.key,
        "report": {"accuracy": 1.0, "curve": {"band": list(CURVE_BANDS),
                                              "share": [1.0] * len(CURVE_BANDS),
                                              "fp": zeros, "fn": zeros}},
    }
    n_in = N_INPUTS["line"]  # Fourier features, where a net has them, are inside it
    return Proxy(meta, {"visibility": constant_net(visibility, n_in),
                        "depth": constant_net(0.0, n_in)})
