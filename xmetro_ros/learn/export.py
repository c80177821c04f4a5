"""ONNX export of fitted models and the model card.

Every exported graph maps raw features (study units, float32) to errors in **mm**:
* point-wise families (DT, SVR, MLP via skl2onnx; CatBoost via its own exporter): input ``X`` (N, F) → output
  ``y`` (N, 1); the µm → mm factor is appended to the graph.
* PointNet: input ``X`` (B, n, F) sets → output ``y`` (B, n, A); how sets are formed is in the card. With the
  spread head (``pointnet_multi``) a second output ``log_sigma`` (B, n, A): log of the predicted σ in mm.

The card (``card.json``) is also embedded in every ONNX file as metadata (``metadata_props['xmetro_card']``).
"""

from __future__ import annotations

import io
import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from .families import TARGET_SCALE

__all__ = ["CARD_KEY", "GLOBAL_FEATURE_DOC", "embed_card", "export_pointnet", "export_pointwise"]

CARD_KEY = "xmetro_card"
GLOBAL_FEATURE_DOC = (
    "PointNet global feature = max over a set of set_size points of the shared-MLP features. At inference the "
    "scan's valid points are split into sets of set_size by a permutation seeded with partition_seed "
    "(numpy default_rng(seed).permutation(M)); the last set is padded by repeating its own points (max-pool "
    "invariant) and every point gets the prediction of the set it falls in. Training used random sets of "
    "set_size points of one cloud (never mixing clouds); test draws used sets of the same size."
)


def _scale_output(model: onnx.ModelProto, factor: float, out_name: str = "y") -> onnx.ModelProto:
    """Append ``y = first_output * factor`` (float32) and make ``y`` (N, 1) the only output."""
    g = model.graph
    src = g.output[0].name
    # Constant nodes, not initializers: CatBoost writes an old IR version where initializers must be inputs.
    g.node.append(helper.make_node("Constant", [], ["xmetro_um_to_mm"],
                                   value=numpy_helper.from_array(np.array([factor], np.float32))))
    g.node.append(helper.make_node("Constant", [], ["xmetro_shape_n1"],
                                   value=numpy_helper.from_array(np.array([-1, 1], np.int64))))
    g.node.append(helper.make_node("Mul", [src, "xmetro_um_to_mm"], ["xmetro_scaled"]))
    g.node.append(helper.make_node("Reshape", ["xmetro_scaled", "xmetro_shape_n1"], [out_name]))
    del g.output[:]
    g.output.append(helper.make_tensor_value_info(out_name, TensorProto.FLOAT, [None, 1]))
    if not any(op.domain in ("", "ai.onnx") for op in model.opset_import):
        model.opset_import.append(helper.make_opsetid("", 13))
    return model


def export_pointwise(family: str, estimator: Any, n_features: int) -> onnx.ModelProto:
    """ONNX graph of a fitted point-wise estimator trained on µm targets; output in mm."""
    if family == "catboost":
        with tempfile.TemporaryDirectory() as tmp:
            p = Path(tmp) / "m.onnx"
            estimator.save_model(str(p), format="onnx", export_parameters={"onnx_domain": "ai.catboost"})
            model = onnx.load(str(p))
        # CatBoost names its input "features": rename to X.
        old = model.graph.input[0].name
        for node in model.graph.node:
            node.input[:] = ["X" if i == old else i for i in node.input]
        model.graph.input[0].name = "X"
    else:
        from skl2onnx import convert_sklearn
        from skl2onnx.common.data_types import FloatTensorType

        model = convert_sklearn(estimator, initial_types=[("X", FloatTensorType([None, n_features]))],
                                target_opset={"": 17, "ai.onnx.ml": 3})
    model = _scale_output(model, 1.0 / TARGET_SCALE)
    onnx.checker.check_model(model)
    return model


def export_pointnet(module: Any, n_features: int, gemm: bool = True, wide: bool = True) -> onnx.ModelProto:
    """ONNX graph of a fitted :class:`~xmetro_ros.learn.pointnet.PointNetReg` (sets (B, n, F) → (B, n, A) mm), with
    its per-point layers as 2-D Gemm nodes (``gemm``; :mod:`.onnx_gemm`: the same outputs, ~20 % faster) and its
    input standardisation and output scaling on whole sets' rows (``wide``; :mod:`.onnx_broadcast`: the same outputs,
    ~25 % faster again)."""
    import torch

    module = module.eval()
    buf = io.BytesIO()
    dummy = torch.zeros(2, 8, n_features)
    # With the spread head a second output ``log_sigma`` (B, n, A), log of σ in mm; ``y`` stays the first output.
    outs = ["y", "log_sigma"] if getattr(module, "head_sigma", None) is not None else ["y"]
    # torch.onnx.export writes to a file-like object too (its stub names paths only)
    torch.onnx.export(module, (dummy,), buf, input_names=["X"], output_names=outs, opset_version=17,  # type: ignore[arg-type]
                      dynamic_axes={"X": {0: "sets", 1: "points"}, **{o: {0: "sets", 1: "points"} for o in outs}},
                      dynamo=False)
    model = onnx.load_from_string(buf.getvalue())
    onnx.checker.check_model(model)
    if gemm:
        from .onnx_gemm import pointwise_gemm

        model, _ = pointwise_gemm(model)
    if wide:
        from .onnx_broadcast import wide_broadcasts

        model, _ = wide_broadcasts(model)
    return model


def embed_card(model: onnx.ModelProto, card: dict) -> onnx.ModelProto:
    """Store the card JSON in the model's metadata (replacing an older one)."""
    keep = [p for p in model.metadata_props if p.key != CARD_KEY]
    del model.metadata_props[:]
    model.metadata_props.extend(keep)
    entry = model.metadata_props.add()
    entry.key, entry.value = CARD_KEY, json.dumps(card, sort_keys=True)
    model.producer_name = "xmetro_ros"
    return model
