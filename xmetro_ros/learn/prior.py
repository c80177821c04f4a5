"""A PointNet prior from an exported model set (``xmetro calibrate --prior MODEL_DIR|default``).

Model sets hold their networks as ONNX only (no framework weights): :func:`load_prior` rebuilds the
:class:`~xmetro_ros.learn.pointnet.PointNetReg` of a set's ``pointnet_multi`` model from the ONNX initializers
(``torch.onnx.export`` folds each ``Linear`` into a ``MatMul`` on the transposed weight, named by its module scope,
plus the bias and the normalisation buffers under their own names), loads it with ``strict=True`` and checks that
the rebuilt network reproduces ONNX Runtime on random sets (within 1e-5 mm, σ too). :func:`check_prior` refuses a
prior that cannot warm-start the network a calibration would train: other features (names and order), another
layout (block1, block2, head, set size) or no spread head. Errors are :class:`PriorError` (a ValueError) with the
prior's directory and the cause.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..judge.inference import model_scanner_id

__all__ = ["PRIOR_FAMILY", "Prior", "PriorError", "check_prior", "load_prior"]

PRIOR_FAMILY = "pointnet_multi"  # the family a prior warm-starts (the node's default, with the spread head)


class PriorError(ValueError):
    """A model set that cannot serve as a prior: the message names its directory and the cause."""


@dataclass
class Prior:
    """A rebuilt prior network and what the card says of it."""

    dir: Path
    module: Any  # PointNetReg
    card: dict[str, Any]
    layout: dict[str, Any]  # block1, block2, head, set_size, sigma_head
    onnx_max_abs_diff_mm: float

    @property
    def feature_names(self) -> list[str]:
        """The prior's input features, in order."""
        return list(self.card["feature_names"])

    def to_dict(self) -> dict[str, Any]:
        """What a calibrated model's card records of its prior."""
        entry = next(m for m in self.card["models"] if m["family"] == PRIOR_FAMILY)
        return {"model_id": self.card.get("id"), "dir": str(self.dir), "family": PRIOR_FAMILY,
                "sha256": entry.get("sha256"),
                "scanner": model_scanner_id(self.card),
                "layout": self.layout, "rebuilt_onnx_max_abs_diff_mm": self.onnx_max_abs_diff_mm,
                "how": "the PointNet starts from the prior's weights and input / target normalisation and is "
                       "fine-tuned on the campaign's training scans (same epochs as from scratch)"}


def _module_key(node_output: str) -> str:
    """``/block1/block1.0/MatMul_output_0`` → ``block1.0``; ``/head_local/MatMul_output_0`` → ``head_local``."""
    parts = [p for p in node_output.split("/") if p]
    return parts[-2] if len(parts) >= 2 else ""


def _state_dict(model: Any) -> dict[str, np.ndarray]:
    from onnx import numpy_helper

    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    state = {k: v for k, v in inits.items() if not k.startswith("onnx::")}
    for node in model.graph.node:
        if node.op_type == "MatMul" and len(node.input) == 2 and node.input[1] in inits:
            state[f"{_module_key(node.output[0])}.weight"] = inits[node.input[1]].T
        elif node.op_type == "Gemm" and len(node.input) >= 2 and node.input[1] in inits:
            w = inits[node.input[1]]
            trans_b = any(a.name == "transB" and a.i for a in node.attribute)
            state[f"{_module_key(node.output[0])}.weight"] = w if trans_b else w.T
    return state


def load_prior(spec: str | Path) -> Prior:
    """The ``pointnet_multi`` network of the model set at ``spec`` (``default``: the packaged model), rebuilt from
    its ONNX and checked against ONNX Runtime. Raises PriorError."""
    import onnx
    import onnxruntime as ort
    import torch

    from ..scan.resources import default_model_dir
    from .pointnet import PointNetReg

    d = default_model_dir() if str(spec) == "default" else Path(spec)
    where = f"prior {d}"
    try:
        card = json.loads((d / "card.json").read_text())
    except (OSError, ValueError) as e:
        raise PriorError(f"{where}: not a model set (card.json cannot be read: {e})") from e
    entries = [m for m in card.get("models", []) if m.get("family") == PRIOR_FAMILY]
    if not entries:
        raise PriorError(f"{where}: has no {PRIOR_FAMILY} model (families "
                         f"{sorted({m.get('family') for m in card.get('models', [])})}); only a {PRIOR_FAMILY} "
                         "network can warm-start the calibration's PointNet")
    entry = entries[0]
    p = entry.get("params") or {}
    try:
        layout: dict[str, Any] = {"block1": [int(x) for x in p["block1"]], "block2": [int(x) for x in p["block2"]],
                  "head": [int(x) for x in p["head"]], "set_size": int(card.get("set_size", p.get("set_size", 0))),
                  "sigma_head": bool(p.get("sigma_head", False))}
    except (KeyError, TypeError, ValueError) as e:
        raise PriorError(f"{where}: its card gives no network layout ({e})") from e
    path = d / entry["file"]
    try:
        model = onnx.load(str(path))
    except (OSError, ValueError) as e:
        raise PriorError(f"{where}: {path.name} cannot be read: {e}") from e
    net = PointNetReg(len(card["feature_names"]), layout["block1"], layout["block2"], layout["head"], n_out=3,
                      sigma_head=layout["sigma_head"])
    state = _state_dict(model)
    try:
        net.load_state_dict({k: torch.from_numpy(np.array(v, dtype=np.float32)) for k, v in state.items()},
                            strict=True)
    except RuntimeError as e:
        raise PriorError(f"{where}: the ONNX graph does not match its card's layout {layout}: {e}") from e
    net.eval()
    rng = np.random.default_rng(0)
    X = (rng.normal(size=(3, layout["set_size"] or 50, len(card["feature_names"]))) * net.x_std.numpy()
         + net.x_mean.numpy()).astype(np.float32)
    outs = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"X": X})
    with torch.no_grad():
        ref = net(torch.from_numpy(X))
    ref = ref if isinstance(ref, tuple) else (ref,)
    diff = max(float(np.max(np.abs(o - r.numpy()))) for o, r in zip(outs, ref, strict=True))
    if not diff <= 1e-5:
        raise PriorError(f"{where}: the network rebuilt from {path.name} differs from ONNX Runtime by {diff:.3g} "
                         "(> 1e-5): not a graph this version exports")
    return Prior(d, net, card, layout, diff)


def check_prior(prior: Prior, feature_names: list[str], config: Any, profile: str) -> None:
    """Refuse (PriorError) a prior that cannot warm-start ``config`` (PointNetConfig of ``profile``) on
    ``feature_names``: the network's inputs, layout and heads must be the same."""
    where = f"prior {prior.dir} ({prior.card.get('id')})"
    if prior.feature_names != list(feature_names):
        raise PriorError(f"{where}: its features {prior.feature_names} are not the calibration's {list(feature_names)}"
                         " (names and order must be equal)")
    want = {"block1": list(config.block1), "block2": list(config.block2), "head": list(config.head),
            "set_size": int(config.set_size), "sigma_head": bool(config.sigma_head)}
    if prior.layout != want:
        diff = ", ".join(f"{k} {prior.layout[k]} (profile {want[k]})" for k in want if prior.layout[k] != want[k])
        raise PriorError(f"{where}: its network layout differs from the {PRIOR_FAMILY} layout of --profile {profile}: "
                         f"{diff}. Choose the profile the prior was trained with (its card's profile: "
                         f"{prior.card.get('profile', '?')}; the compact layout of quick, full and default is the "
                         "same), or another prior")
