"""Rewrite model sets' PointNet files as ``xmetro export-default`` writes them now, in place: per-point layers as
2-D Gemm nodes (xmetro_ros/learn/onnx_gemm.py, since 0.9.3) and the input standardisation and output scaling on whole
sets' rows (xmetro_ros/learn/onnx_broadcast.py, since 0.9.4), after checking that ONNX Runtime gives the same bits as
the original graph on random sets; the card's sha256 of each rewritten file is updated. A file already written that
way is left as it is.

    python tools/gemm_models.py DIR [DIR ...]   # e.g. xmetro_ros/models/default xmetro_ros/models/posed
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort

from xmetro_ros.judge.inference import session_options
from xmetro_ros.learn.onnx_broadcast import wide_broadcasts
from xmetro_ros.learn.onnx_gemm import pointwise_gemm


def _outputs(model: onnx.ModelProto, X: np.ndarray) -> list[np.ndarray]:
    s = ort.InferenceSession(model.SerializeToString(), session_options(1), providers=["CPUExecutionProvider"])
    return s.run(None, {s.get_inputs()[0].name: X})


def rewrite_dir(d: Path) -> None:
    card_path = d / "card.json"
    card = json.loads(card_path.read_text())
    n_features = len(card["feature_names"])
    rng = np.random.default_rng(0)
    for entry in card["models"]:
        if entry["kind"] != "sets":
            continue
        p = d / entry["file"]
        old = onnx.load(str(p))
        new, layers = pointwise_gemm(old)
        new, steps = wide_broadcasts(new)
        if layers + steps == 0:
            print(f"{p}: nothing to rewrite")
            continue
        for shape in ((128, 50, n_features), (3, 1, n_features), (1, 7, n_features)):
            X = rng.normal(size=shape).astype(np.float32) * 3.0
            for a, b in zip(_outputs(old, X), _outputs(new, X), strict=True):
                if not np.array_equal(a, b):
                    raise SystemExit(f"{p}: the rewritten graph differs from the original on sets {shape}")
        data = new.SerializeToString()
        p.write_bytes(data)
        entry["sha256"] = hashlib.sha256(data).hexdigest()
        print(f"{p}: {layers} layers as Gemm, {steps} broadcasts on rows, the same bits on random sets; "
              f"sha256 {entry['sha256'][:12]}")
    card_path.write_text(json.dumps(card, indent=1, sort_keys=True))


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    for arg in sys.argv[1:]:
        rewrite_dir(Path(arg))
