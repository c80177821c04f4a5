"""SHAP explanations of a model set with exact additivity (base + Σ SHAP == prediction).

Scheme: antithetic permutation SHAP (the PermutationExplainer's scheme) over a small background set, run on the
ONNX model set with every coalition of every point predicted in one batched call. For a permutation π and a
background row b, features are switched from b to x in the order of π; each feature's SHAP value is the mean of
its marginal changes. The marginal changes telescope, so Σ_k φ_k = f(x) − mean_b f(b) holds exactly (up to float64
rounding) for any number of permutations; base = mean_b f(b). With a PointNet member, every coalition state of the
P explained points is predicted as one cloud with the same set partition as ``ModelSet.predict``, so f(x) is exactly
the prediction the node publishes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ShapResult", "explain", "global_ranking"]


@dataclass
class ShapResult:
    """base_values (A,) mm, shap (P, F, A) mm, predictions (P, A) mm, for the requested axes (in order)."""

    base_values: np.ndarray
    shap: np.ndarray
    predictions: np.ndarray
    feature_names: list[str]
    axes: tuple[int, ...]


def explain(
    model_set,
    X: np.ndarray,
    background: np.ndarray | None = None,
    axes: tuple[int, ...] = (0, 1, 2),
    n_permutations: int = 2,
    max_background: int = 10,
    seed: int = 0,
) -> ShapResult:
    """SHAP values of ``model_set`` (a :class:`~xmetro_ros.inference.ModelSet`) for the rows X (P, F).

    background: (B, F) reference rows (None → the card's stored background, else the column medians of X);
    at most ``max_background`` rows are used (evenly spaced). ``n_permutations`` is rounded up to an even number
    (antithetic pairs). Raises ValueError for bad shapes, non-finite rows or unknown axes.
    """
    X = np.asarray(X, np.float32)
    n_f = len(model_set.feature_names)
    if X.ndim != 2 or X.shape[1] != n_f:
        raise ValueError(f"explain: X must be (P, {n_f}), got {X.shape}")
    if len(X) == 0:
        raise ValueError("explain: no points to explain")
    if not np.all(np.isfinite(X)):
        raise ValueError("explain: X has non-finite features")
    axes = tuple(int(a) for a in axes)
    if not axes or any(a not in (0, 1, 2) for a in axes):
        raise ValueError(f"explain: axes must be a non-empty subset of (0, 1, 2), got {axes}")
    if background is None:
        stored = model_set.card.get("background")
        background = np.asarray(stored, np.float32) if stored else np.median(X, axis=0, keepdims=True)
    bg = np.asarray(background, np.float32)
    if bg.ndim != 2 or bg.shape[1] != n_f or len(bg) == 0 or not np.all(np.isfinite(bg)):
        raise ValueError(f"explain: background must be finite (B, {n_f}) with B ≥ 1, got {bg.shape}")
    if len(bg) > max_background:
        bg = bg[np.linspace(0, len(bg) - 1, max_background).round().astype(int)]

    rng = np.random.default_rng(seed)
    n_pairs = max(1, (int(n_permutations) + 1) // 2)
    perms = []
    for _ in range(n_pairs):
        p = rng.permutation(n_f)
        perms += [p, p[::-1]]
    P, B, F = len(X), len(bg), n_f
    # states[j, b, s] : coalition after s switches of permutation j from background b to x.
    states = np.empty((len(perms), B, F + 1, P, F), np.float32)
    for j, perm in enumerate(perms):
        cur = np.broadcast_to(bg[:, None, :], (B, P, F)).copy()
        states[j, :, 0] = cur
        for s, k in enumerate(perm, start=1):
            cur[:, :, k] = X[None, :, k]
            states[j, :, s] = cur
    pred = model_set.predict_batch(states.reshape(-1, P, F)).reshape(len(perms), B, F + 1, P, 3)[..., axes]
    deltas = np.diff(pred, axis=2)  # (J, B, F, P, A): change when the s-th feature of the permutation switches
    phi = np.zeros((P, F, len(axes)))
    for j, perm in enumerate(perms):
        phi[:, perm, :] += deltas[j].sum(axis=0).transpose(1, 0, 2)
    phi /= len(perms) * B
    base = pred[:, :, 0].mean(axis=(0, 1, 2))  # f(b): the same for every point (a cloud of copies of b)
    predictions = pred[0, 0, F]  # f(x): identical for every j, b
    return ShapResult(base_values=np.asarray(base), shap=phi, predictions=predictions,
                      feature_names=list(model_set.feature_names), axes=axes)


def global_ranking(shap_values: np.ndarray, feature_names: list[str]) -> list[tuple[str, float]]:
    """Features sorted by mean |SHAP| (one axis: shap_values (P, F))."""
    imp = np.abs(np.asarray(shap_values)).mean(axis=0)
    order = np.argsort(-imp)
    return [(feature_names[i], float(imp[i])) for i in order]
