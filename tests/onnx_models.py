"""Small real ONNX graphs for the tests, built with the ``onnx`` package.

``rust_rail_model``: a rule the synthetic camera images satisfy. The synthetic rails are
rust-brown (R > G > B clearly), ballast, sleepers and concrete are grey, grass and trees
green, sky blue. Per pixel, with R, G, B in 0..255 recovered from the normalised input,

    score = min(R - G - t_rg, R - B - t_rb)

is the logit of the rail class; a background class has the constant logit ``margin`` and
all other classes 0, so ArgMax picks the rail class where ``score > margin``. Ops: Conv
(1x1, undoing the normalisation), Split, Min, Conv (1x1 to 19 channels), optional ArgMax.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

RAIL_RAISED = 17
TERRAIN = 9


def rust_rail_model(
    path: str | Path,
    mean: Sequence[float] = (0.485, 0.456, 0.406),
    std: Sequence[float] = (0.229, 0.224, 0.225),
    n_classes: int = 19,
    rail_class: int = RAIL_RAISED,
    background_class: int = TERRAIN,
    t_rg: float = 6.0,
    t_rb: float = 12.0,
    margin: float = 0.5,
    output: str = "logits",
    downsample: int = 1,
) -> Path:
    """Write the rule model to ``path``; ``output`` is "logits" (1, C, h, w) or "labels"
    (1, h, w) int64; ``downsample`` > 1 makes the output smaller than the input (like
    DDRNet's 1/8) with a strided first convolution."""
    mean_a = np.asarray(mean, dtype=np.float64)
    std_a = np.asarray(std, dtype=np.float64)
    # channel value in 0..255: 255 * (std * x + mean)
    scale = 255.0 * std_a
    offs = 255.0 * mean_a
    w1 = np.zeros((2, 3, 1, 1), np.float32)
    b1 = np.zeros(2, np.float32)
    w1[0, 0], w1[0, 1] = scale[0], -scale[1]  # R - G
    b1[0] = offs[0] - offs[1] - t_rg
    w1[1, 0], w1[1, 2] = scale[0], -scale[2]  # R - B
    b1[1] = offs[0] - offs[2] - t_rb
    w2 = np.zeros((n_classes, 1, 1, 1), np.float32)
    w2[rail_class] = 1.0
    b2 = np.zeros(n_classes, np.float32)
    b2[background_class] = margin
    inits = [
        numpy_helper.from_array(w1, "w1"),
        numpy_helper.from_array(b1, "b1"),
        numpy_helper.from_array(w2, "w2"),
        numpy_helper.from_array(b2, "b2"),
        numpy_helper.from_array(np.array([1, 1], np.int64), "split"),
    ]
    s = int(downsample)
    nodes = [
        helper.make_node("Conv", ["input", "w1", "b1"], ["diff"], strides=[s, s]),
        helper.make_node("Split", ["diff", "split"], ["rg", "rb"], axis=1),
        helper.make_node("Min", ["rg", "rb"], ["score"]),
        helper.make_node("Conv", ["score", "w2", "b2"], ["logits"]),
    ]
    out_name = "logits"
    if output == "labels":
        nodes.append(helper.make_node("ArgMax", ["logits"], ["labels"], axis=1, keepdims=0))
        out_name = "labels"
        out = helper.make_tensor_value_info("labels", TensorProto.INT64, [1, "h", "w"])
    elif output == "logits":
        out = helper.make_tensor_value_info("logits", TensorProto.FLOAT, [1, n_classes, "h", "w"])
    else:
        raise ValueError("output must be 'logits' or 'labels'")
    graph = helper.make_graph(
        nodes,
        "rust_rail_rule",
        [helper.make_tensor_value_info("input", TensorProto.FLOAT, [1, 3, "H", "W"])],
        [out],
        inits,
    )
    assert out_name in (o.name for o in graph.output)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    path = Path(path)
    onnx.save(model, str(path))
    return path
