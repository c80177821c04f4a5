"""SHAP explanations of a model set with exact additivity (base + Σ SHAP == prediction).

Scheme: antithetic permutation SHAP (the PermutationExplainer's scheme) over a small background set, run on the
ONNX model set with every coalition of every point predicted in batched calls. For a permutation π and a background
row b, players are switched from b to x in the order of π; each player's SHAP value is the mean of its marginal
changes. The marginal changes telescope, so Σ_k φ_k = f(x) − mean_b f(b) holds exactly (up to float64 rounding) for
any number of permutations; base = mean_b f(b), the prediction for a cloud of copies of b.

Two uses:
* :func:`explain` explains rows X predicted together as one cloud (the study's SHAP plots: test sets).
* :func:`explain_in_cloud` explains rows of a judged scan exactly as the node published them. With a PointNet member
  a point's prediction also depends on the other points of its set (the max-pooled global feature), so one more
  player, :data:`SET_CONTEXT` ("the rest of its set"), switches the other members of the point's own set (the
  partition ``ModelSet.predict`` used) from b to their actual features. Then base + Σ SHAP equals the published
  deviation exactly, the base is the same for every point, and the context player's share says how much of a
  point's prediction its set neighbours carry. Point-wise models need no context player (their prediction depends on
  the row alone) and get the plain scheme.

With a card calibrated per surface class, U's multiplier depends on each point's class (from the scan's curvature,
not a feature). Explaining U with the classes adds the player :data:`SURFACE_CLASS`: off, a point takes the
all-class multiplier (so the base stays the same for every point), on, its own class's; its share says how much the
point's shape moves its U, and base + Σ SHAP equals the published U.

With a card that carries d and U onto the measured normal (:mod:`.along_normal`), the published outputs of the rows
it changes are d' = (d·n)·n and U' = U_n(noise)·(…); explaining them adds the player :data:`ALONG_NORMAL`: off, the
model's d or U; on, the point's published d' or U'. The base stays the same for every point, base + Σ SHAP equals
the published output, and the player's share says how much carrying onto the normal moved it (for U', whose value
no feature moves, the features share only what the model's U would have been).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .along_normal import AlongNormalRows

__all__ = ["ALONG_NORMAL", "OUTPUTS", "SET_CONTEXT", "SURFACE_CLASS", "ShapResult", "explain", "explain_in_cloud",
           "global_ranking"]

# Name of the extra player of :func:`explain_in_cloud` for set models: the other points of the point's set.
SET_CONTEXT = "set_context"
# Name of the player of an explanation of U with surface classes: the point's class (off: the all-class multiplier).
SURFACE_CLASS = "surface_class"
# Name of the player of an explanation with a card's along-normal block: the point carried onto its normal.
ALONG_NORMAL = "along_normal"
#: What can be explained: the predicted error, or its expanded uncertainty U.
OUTPUTS = ("error", "uncertainty")


@dataclass
class ShapResult:
    """base_values (A,) mm, shap (P, F, A) mm, predictions (P, A) mm, for the requested axes (in order).

    ``feature_names`` names the F players: the model's features, plus :data:`SET_CONTEXT` last where
    :func:`explain_in_cloud` explained a set model.
    """

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
    output: str = "error",
    surface_class: np.ndarray | None = None,
    noise: np.ndarray | None = None,
    along: AlongNormalRows | None = None,
) -> ShapResult:
    """SHAP values of ``model_set`` (a :class:`~xmetro_ros.judge.inference.ModelSet`) for the rows X (P, F).

    output: "error" (the predicted error) or "uncertainty" (its expanded uncertainty U, which features make a point
    uncertain; needs a calibrated model set). Additivity holds for either. ``surface_class`` (P,): with "uncertainty",
    each row's surface class, a player of its own (:data:`SURFACE_CLASS`, module doc; None: the all-class U);
    ``noise`` (P,) mm: each row's measured noise, switched on and off with the class (the card's U takes both
    together, :mod:`.measured_noise`). ``along``: the card's along-normal block applied to the P rows
    (``ModelSet.along_normal_rows``), a player of its own (:data:`ALONG_NORMAL`; None: the model's outputs).

    background: (B, F) reference rows (None → the card's stored background, else the column medians of X);
    at most ``max_background`` rows are used (evenly spaced). ``n_permutations`` is rounded up to an even number
    (antithetic pairs). Raises ValueError for bad shapes, non-finite rows or unknown axes.
    """
    X = _check_rows(model_set, X, axes)
    axes = tuple(int(a) for a in axes)
    _check_output(output)
    bg = _background(model_set, X, background, max_background)
    P, B, F = len(X), len(bg), X.shape[1]
    cls = None if surface_class is None or output != "uncertainty" else np.asarray(surface_class).reshape(P)
    i_an = F + (cls is not None) if along is not None else -1
    players = F + (cls is not None) + (along is not None)  # the features, the surface class, the along-normal
    perms = _permutations(players, n_permutations, seed)
    state_an = np.zeros((len(perms), players + 1), bool)
    # states[j, b, s] : coalition after s switches of permutation j from background b to x.
    states = np.empty((len(perms), B, players + 1, P, F), np.float32)
    state_cls = np.full((len(perms), players + 1, P), -1, np.int8)  # −1: the all-class multiplier
    nz = None if cls is None or noise is None else np.asarray(noise, np.float64).reshape(P)
    state_nz = np.full((len(perms), players + 1, P), np.nan)  # NaN: no measured noise (σ̂ alone)
    for j, perm in enumerate(perms):
        cur = np.broadcast_to(bg[:, None, :], (B, P, F)).copy()
        states[j, :, 0] = cur
        for s, k in enumerate(perm, start=1):
            if k < F:
                cur[:, :, k] = X[None, :, k]
            elif k == i_an:
                state_an[j, s:] = True
            else:
                state_cls[j, s:] = cls
                if nz is not None:
                    state_nz[j, s:] = nz
            states[j, :, s] = cur
    kw = {} if cls is None else {
        "surface_class": np.broadcast_to(state_cls[:, None], (len(perms), B, players + 1, P)).reshape(-1, P)}
    if nz is not None:
        kw["noise"] = np.broadcast_to(state_nz[:, None], (len(perms), B, players + 1, P)).reshape(-1, P)
    pred = model_set.predict_batch(states.reshape(-1, P, F), output=output, **kw)
    pred = pred.reshape(len(perms), B, players + 1, P, 3)
    if along is not None:
        pred = np.where(state_an[:, None, :, None, None], along.carry(pred, output), pred)
    names = (list(model_set.feature_names) + ([SURFACE_CLASS] if cls is not None else [])
             + ([ALONG_NORMAL] if along is not None else []))
    return _shapley(pred[..., axes], perms, names, axes)


def explain_in_cloud(
    model_set,
    X_cloud: np.ndarray,
    rows: np.ndarray,
    background: np.ndarray | None = None,
    axes: tuple[int, ...] = (0, 1, 2),
    n_permutations: int = 2,
    max_background: int = 10,
    seed: int = 0,
    max_set_rows: int = 4_000_000,
    output: str = "error",
    surface_class: np.ndarray | None = None,
    noise: np.ndarray | None = None,
    along: AlongNormalRows | None = None,
) -> ShapResult:
    """SHAP values of the published predictions of ``rows`` of a cloud (see the module docstring).

    X_cloud: (M, F) finite feature rows predicted together by ``model_set.predict`` (a judged scan's finite rows,
    in order); rows: (P,) indices into it. For a set model the background is thinned (evenly spaced) so that at most
    ``max_set_rows`` feature rows are predicted; additivity is exact whatever the background. Raises ValueError for
    bad shapes, non-finite rows, rows out of range or unknown axes. ``output``: as :func:`explain` (with
    "uncertainty", base + Σ SHAP equals the published U: give ``surface_class`` (M,), the classes the judge gave
    the cloud's rows, when the card is calibrated per class, and ``noise`` (M,), the measured noise its U took).
    ``along``: the card's along-normal block applied to the cloud's M rows (``ModelSet.along_normal_rows``), whose
    published outputs it changed (player :data:`ALONG_NORMAL`).
    """
    _check_output(output)
    X_cloud = np.asarray(X_cloud, np.float32)
    rows = np.asarray(rows, np.int64).reshape(-1)
    if X_cloud.ndim != 2 or X_cloud.shape[1] != len(model_set.feature_names):
        raise ValueError(f"explain: the cloud must be (M, {len(model_set.feature_names)}), got {X_cloud.shape}")
    if len(rows) and (rows.min() < 0 or rows.max() >= len(X_cloud)):
        raise ValueError(f"explain: rows out of range [0, {len(X_cloud)})")
    cls = None
    if surface_class is not None and output == "uncertainty":
        cls = np.asarray(surface_class).reshape(-1)
        if len(cls) != len(X_cloud):
            raise ValueError(f"explain: {len(cls)} surface classes for a cloud of {len(X_cloud)} rows")
    nz = None
    if cls is not None and noise is not None:
        nz = np.asarray(noise, np.float64).reshape(-1)
        if len(nz) != len(X_cloud):
            raise ValueError(f"explain: {len(nz)} noise scales for a cloud of {len(X_cloud)} rows")
    if along is not None and len(along.use) != len(X_cloud):
        raise ValueError(f"explain: along-normal rows for {len(along.use)} rows, a cloud of {len(X_cloud)}")
    own_an = None if along is None else along.take(rows)
    if not model_set.has_sets:
        return explain(model_set, X_cloud[rows], background, axes=axes, n_permutations=n_permutations,
                       max_background=max_background, seed=seed, output=output,
                       surface_class=None if cls is None else cls[rows], noise=None if nz is None else nz[rows],
                       along=own_an)
    if not np.all(np.isfinite(X_cloud)):
        raise ValueError("explain: the cloud has non-finite features (predict leaves them out of every set)")
    X = _check_rows(model_set, X_cloud[rows], axes)
    axes = tuple(int(a) for a in axes)
    from .pointsets import set_membership

    P, F, M, n = len(X), X.shape[1], len(X_cloud), model_set.set_size
    idx, set_of = set_membership(M, n, model_set.partition_seed)
    members = idx[set_of[rows]]  # (P, n) cloud rows of each explained point's set (padding repeats members)
    is_self = members == rows[:, None]  # where the point itself sits (more than once if padded with itself)
    first = is_self.argmax(axis=1)
    players = F + 1 + (cls is not None) + (along is not None)  # features, set context, surface class, along-normal
    perms = _permutations(players, n_permutations, seed)
    steps = players + 1
    budget_b = max(1, int(max_set_rows) // max(1, P * len(perms) * steps * n))
    bg = _background(model_set, X, background, min(max_background, budget_b))
    B, J = len(bg), len(perms)
    # Per permutation: the point's feature mask, the context flag (and the class flag) after s switches.
    on = np.zeros((J, steps, players), bool)
    for j, perm in enumerate(perms):
        for s, k in enumerate(perm, start=1):
            on[j, s:, k] = True
    pred = np.empty((J, B, steps, P, len(axes)))
    predict_sets = model_set.predict_sets if output == "error" else model_set.predict_sets_uncertainty
    own_cls = None if cls is None else cls[rows]
    own_nz = None if nz is None else nz[rows]
    chunk = max(1, 250_000 // (J * B * steps * n))  # points per batch: ~250k feature rows per ONNX call
    for c0 in range(0, P, chunk):
        c = slice(c0, min(P, c0 + chunk))
        pc = c.stop - c.start
        actual = X_cloud[members[c]]  # (pc, n, F)
        # Sets of every state: the context rows at b (off) or actual (on), the point's own rows at the mix.
        sets = np.where(on[:, None, :, None, None, None, F], actual[None, None, None],
                        bg[None, :, None, None, None, :])  # (J, B, steps, pc, n, F)
        own = np.where(on[:, None, :, None, :F], X[None, None, None, c], bg[None, :, None, None, :])  # (J,B,S,pc,F)
        sel = np.broadcast_to(is_self[c][None, None, None, :, :, None], sets.shape)
        sets[sel] = np.broadcast_to(own[:, :, :, :, None, :], sets.shape)[sel]
        if own_cls is None:
            y = predict_sets(sets.reshape(-1, n, F)).reshape(J, B, steps, pc, n, 3)
        else:  # the point's class once its player is on, else none (−1); only its own output is read
            st = np.where(on[:, :, F + 1][:, :, None], own_cls[c][None, None, :], -1)  # (J, steps, pc)
            sc = np.broadcast_to(st[:, None, :, :, None], (J, B, steps, pc, n)).reshape(-1, n)
            sn = None
            if own_nz is not None:  # the measured noise with the class (NaN: σ̂ alone)
                sv = np.where(on[:, :, F + 1][:, :, None], own_nz[c][None, None, :], np.nan)
                sn = np.broadcast_to(sv[:, None, :, :, None], (J, B, steps, pc, n)).reshape(-1, n)
            y = model_set.predict_sets_uncertainty(sets.reshape(-1, n, F), sc, sn).reshape(J, B, steps, pc, n, 3)
        yc = y[:, :, :, np.arange(pc), first[c]]  # (J, B, steps, pc, 3)
        if own_an is not None:  # the point's published d' / U' once its player is on (the last one)
            an_on = on[:, :, players - 1][:, None, :, None, None]
            yc = np.where(an_on, own_an.take(np.arange(c.start, c.stop)).carry(yc, output), yc)
        pred[:, :, :, c] = yc[..., axes]
    names = ([*list(model_set.feature_names), SET_CONTEXT] + ([SURFACE_CLASS] if cls is not None else [])
             + ([ALONG_NORMAL] if along is not None else []))
    return _shapley(pred, perms, names, axes)


def _check_output(output: str) -> None:
    if output not in OUTPUTS:
        raise ValueError(f"explain: output must be one of {OUTPUTS}, got {output!r}")


def _check_rows(model_set, X: np.ndarray, axes) -> np.ndarray:
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
    return X


def _background(model_set, X: np.ndarray, background: np.ndarray | None, max_background: int) -> np.ndarray:
    """(B, F) reference rows: given, else the card's stored background, else the column medians of X; at most
    ``max_background`` rows (evenly spaced)."""
    n_f = X.shape[1]
    if background is None:
        stored = model_set.card.get("background")
        background = np.asarray(stored, np.float32) if stored else np.median(X, axis=0, keepdims=True)
    bg = np.asarray(background, np.float32)
    if bg.ndim != 2 or bg.shape[1] != n_f or len(bg) == 0 or not np.all(np.isfinite(bg)):
        raise ValueError(f"explain: background must be finite (B, {n_f}) with B ≥ 1, got {bg.shape}")
    if len(bg) > max_background:
        bg = bg[np.linspace(0, len(bg) - 1, max(1, max_background)).round().astype(int)]
    return bg


def _permutations(n_players: int, n_permutations: int, seed: int) -> list[np.ndarray]:
    """Antithetic pairs of random player orders (``n_permutations`` rounded up to an even number)."""
    rng = np.random.default_rng(seed)
    perms = []
    for _ in range(max(1, (int(n_permutations) + 1) // 2)):
        p = rng.permutation(n_players)
        perms += [p, p[::-1]]
    return perms


def _shapley(pred: np.ndarray, perms: list[np.ndarray], names: list[str], axes: tuple[int, ...]) -> ShapResult:
    """SHAP values from the predictions pred (J, B, players + 1, P, A) of every coalition state."""
    J, B, S, P, A = pred.shape
    deltas = np.diff(pred, axis=2)  # (J, B, players, P, A): change when the s-th player of the permutation switches
    phi = np.zeros((P, S - 1, A))
    for j, perm in enumerate(perms):
        phi[:, perm, :] += deltas[j].sum(axis=0).transpose(1, 0, 2)
    phi /= J * B
    base = pred[:, :, 0].mean(axis=(0, 1, 2))  # f(b): the same for every point (a cloud of copies of b)
    predictions = pred[0, 0, S - 1]  # f(x): identical for every j, b
    return ShapResult(base_values=np.asarray(base), shap=phi, predictions=predictions, feature_names=names,
                      axes=axes)


def global_ranking(shap_values: np.ndarray, feature_names: list[str]) -> list[tuple[str, float]]:
    """Features sorted by mean |SHAP| (one axis: shap_values (P, F))."""
    imp = np.abs(np.asarray(shap_values)).mean(axis=0)
    order = np.argsort(-imp)
    return [(feature_names[i], float(imp[i])) for i in order]
