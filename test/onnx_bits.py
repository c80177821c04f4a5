"""Helpers of the ONNX rewrite tests (test_onnx_gemm, test_onnx_broadcast): run a model in ONNX Runtime as the node
does, and check that a rewritten graph gives the same outputs to the bit on sets of several shapes."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np


def run(model, X: np.ndarray) -> list[np.ndarray]:
    """Every output of ``model`` (an onnx ModelProto) on the input ``X`` (sets, points, features), one thread."""
    import onnxruntime as ort

    from xmetro_ros.judge.inference import session_options

    s = ort.InferenceSession(model.SerializeToString(), session_options(1), providers=["CPUExecutionProvider"])
    return s.run(None, {"X": X})


def assert_same_bits(plain, rewritten, shapes: Iterable[tuple[int, int, int]], n_outputs: int) -> None:
    """``rewritten`` gives ``plain``'s ``n_outputs`` outputs, shapes and bits, on random inputs of each shape."""
    rng = np.random.default_rng(1)
    for shape in shapes:
        X = (rng.normal(size=shape) * 3.0).astype(np.float32)
        want, got = run(plain, X), run(rewritten, X)
        assert len(want) == len(got) == n_outputs
        for a, b in zip(want, got, strict=True):
            assert a.shape == b.shape
            np.testing.assert_array_equal(a, b)
