"""Export trained KSNN weights as the predictor ONNX file read by ``models.predictor.SkinPredictor``.

The graph is built directly from NumPy weights (no tracing): normalization, then per axis two 2-D MatMuls
with bias and tanh, then the three axis outputs stacked into (B, V, 3). Keeping every weight a 2-D MatMul
initializer lets onnxruntime's MatMulNBits quantizer make the optional int8 variant.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from models.atomic import write_bytes
from models.predictor import (
    AXES,
    FORMAT,
    FORMAT_VERSION,
    INPUT_NAME,
    META_PREFIX,
    OUTPUT_NAME,
    KsnnWeights,
    actuator_metadata,
    encode_array,
)

OPSET = 17


def build_model(weights: KsnnWeights, metadata: Mapping[str, str]):
    """Build the ONNX ModelProto for ``weights`` with ``metadata`` (keys without the ``likeness.`` prefix)."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    A, H, V = weights.n_actuators, weights.hidden, weights.n_vertices

    def init(name: str, arr: np.ndarray):
        return numpy_helper.from_array(np.ascontiguousarray(arr, dtype=np.float32), name)

    inits = [init("ksnn.lo", weights.lo), init("ksnn.inv_range", 1.0 / (weights.hi - weights.lo))]
    nodes = [
        helper.make_node("Sub", [INPUT_NAME, "ksnn.lo"], ["p_shift"], name="normalize_sub"),
        helper.make_node("Mul", ["p_shift", "ksnn.inv_range"], ["p_hat"], name="normalize_mul"),
    ]
    inits.append(numpy_helper.from_array(np.array([2], dtype=np.int64), "ksnn.axis2"))
    stacked = []
    for k, ax in enumerate(AXES):
        inits += [init(f"ksnn.{ax}.W1", weights.W1[k]), init(f"ksnn.{ax}.b1", weights.b1[k]),
                  init(f"ksnn.{ax}.W2", weights.W2[k]), init(f"ksnn.{ax}.b2", weights.b2[k])]
        nodes += [
            helper.make_node("MatMul", ["p_hat", f"ksnn.{ax}.W1"], [f"{ax}_z1"], name=f"{ax}_matmul1"),
            helper.make_node("Add", [f"{ax}_z1", f"ksnn.{ax}.b1"], [f"{ax}_a1"], name=f"{ax}_bias1"),
            helper.make_node("Tanh", [f"{ax}_a1"], [f"{ax}_h"], name=f"{ax}_tanh"),
            helper.make_node("MatMul", [f"{ax}_h", f"ksnn.{ax}.W2"], [f"{ax}_z2"], name=f"{ax}_matmul2"),
            helper.make_node("Add", [f"{ax}_z2", f"ksnn.{ax}.b2"], [f"{ax}_y"], name=f"{ax}_bias2"),
            helper.make_node("Unsqueeze", [f"{ax}_y", "ksnn.axis2"], [f"{ax}_col"], name=f"{ax}_unsqueeze"),
        ]
        stacked.append(f"{ax}_col")
    nodes.append(helper.make_node("Concat", stacked, [OUTPUT_NAME], axis=2, name="stack_axes"))
    graph = helper.make_graph(
        nodes, "ksnn",
        [helper.make_tensor_value_info(INPUT_NAME, TensorProto.FLOAT, ["batch", A])],
        [helper.make_tensor_value_info(OUTPUT_NAME, TensorProto.FLOAT, ["batch", V, 3])],
        initializer=inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="likeness")
    model.ir_version = 8
    helper.set_model_props(model, {META_PREFIX + k: v for k, v in metadata.items()})
    onnx.checker.check_model(model)
    del H
    return model


def predictor_metadata(*, head: str, names: Sequence[str], units: Sequence[str], weights: KsnnWeights,
                       base_vertices: np.ndarray, faces: np.ndarray, face_unit_names: Sequence[str] = (),
                       face_unit_offsets: np.ndarray | None = None,
                       training: Mapping[str, Any] | None = None) -> dict[str, str]:
    """The metadata entries of a predictor file (see ``models.predictor`` for the format)."""
    meta = {
        "format": FORMAT,
        "format_version": str(FORMAT_VERSION),
        "head": head,
        "units": "m",
        "actuators": actuator_metadata(names, units, weights.lo, weights.hi),
        "hidden": str(weights.hidden),
        "n_vertices": str(weights.n_vertices),
        "base_vertices": encode_array(base_vertices, "f4"),
        "faces": encode_array(faces, "i4"),
        "training": json.dumps(dict(training or {})),
    }
    if face_unit_offsets is not None and len(face_unit_names):
        meta["face_units"] = json.dumps(list(face_unit_names))
        meta["face_unit_offsets"] = encode_array(face_unit_offsets, "f4")
    return meta


def save_model(model, path: str | Path) -> Path:
    """Write an ONNX model atomically (temp file in the same folder, then rename)."""
    return write_bytes(path, model.SerializeToString())


def export_predictor(path: str | Path, weights: KsnnWeights, metadata: Mapping[str, str]) -> Path:
    """Build and write the float32 predictor file."""
    return save_model(build_model(weights, metadata), path)


def export_int8(float_path: str | Path, path: str | Path, block_size: int = 32) -> Path:
    """Write the int8 variant of a predictor: onnxruntime MatMulNBits, 8 bits, symmetric, accuracy_level 4."""
    import onnx
    from onnxruntime.quantization.matmul_nbits_quantizer import MatMulNBitsQuantizer

    model = onnx.load(str(float_path))
    # Only the output layers: the 13×H input layers are tiny, and quantizing them only adds error.
    quant = MatMulNBitsQuantizer(model, bits=8, block_size=block_size, is_symmetric=True, accuracy_level=4,
                                 nodes_to_exclude=[f"{ax}_matmul1" for ax in AXES])
    quant.process()
    out = quant.model.model
    props = {p.key: p.value for p in model.metadata_props}
    props[META_PREFIX + "quantization"] = json.dumps({"bits": 8, "block_size": block_size, "symmetric": True,
                                                      "accuracy_level": 4, "layers": "output"})
    del out.metadata_props[:]
    onnx.helper.set_model_props(out, props)
    return save_model(out, path)
