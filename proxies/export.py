"""ONNX export of one proxy net (legacy TorchScript exporter: no onnxscript needed)."""

from __future__ import annotations

import io
import warnings

import torch
from torch import nn

OPSET = 17
INPUT_NAME, OUTPUT_NAME = "x", "y"


def export_onnx(net: nn.Module, n_in: int) -> bytes:
    """Serialised ONNX model of `net` with a dynamic batch axis: x (n, n_in) -> y (n,)."""
    buf = io.BytesIO()
    was_training = net.training
    net.eval()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(
            net, (torch.zeros(2, n_in),), buf,
            input_names=[INPUT_NAME], output_names=[OUTPUT_NAME],
            dynamic_axes={INPUT_NAME: {0: "n"}, OUTPUT_NAME: {0: "n"}},
            opset_version=OPSET, dynamo=False,
        )
    net.train(was_training)
    return buf.getvalue()
