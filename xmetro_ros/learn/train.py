"""Fit the study's model families and export model sets the node can load.

* :func:`fit_model` — one family on one table (per axis for DT/SVR/MLP/CatBoost/PointNet, all three axes for
  ``pointnet_multi``): randomized search with k-fold CV driven by MAE, then a refit on all training points.
* :func:`export_model_set` — ONNX files + card (features with units, axes, domain, background, metrics, data
  manifest, how the PointNet global feature is formed) in a directory ``ModelSet.load`` accepts.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from sklearn.model_selection import GroupKFold, KFold, RandomizedSearchCV

from ..judge.inference import AXES, CARD_FORMAT
from .export import GLOBAL_FEATURE_DOC, embed_card, export_pointnet, export_pointwise
from .families import (
    POINTWISE_FAMILIES,
    TARGET_SCALE,
    Profile,
    check_family,
    get_profile,
    make_estimator,
    search_space,
    validate_space,
)
from .pointnet import STUDY_LAYOUT, PointNetConfig, PointNetRegressor

__all__ = ["DOMAIN_MARGIN", "FittedModel", "export_model_set", "feature_units", "fit_model"]

DOMAIN_MARGIN = 0.05  # fraction of each feature's training range added on both sides of the domain


@dataclass
class FittedModel:
    """A fitted family for ``axes`` (indices into x, y, z). ``predict`` returns (M, len(axes)) mm."""

    family: str
    axes: tuple[int, ...]
    estimator: Any
    params: dict = field(default_factory=dict)
    cv_mae: float | None = None
    fit_s: float = 0.0
    spread: Any = None  # optional spread model (CatBoost RMSEWithUncertainty), framework only (not exported)

    @property
    def kind(self) -> str:
        return "sets" if self.family.startswith("pointnet") else "points"

    def predict(self, X: np.ndarray, groups: np.ndarray | None = None) -> np.ndarray:
        X = np.asarray(X, np.float32)
        if self.kind == "sets":
            return np.asarray(self.estimator.predict(X, groups), np.float64)
        return (np.asarray(self.estimator.predict(X), np.float64) / TARGET_SCALE).reshape(len(X), 1)

    def predict_sigma(self, X: np.ndarray, groups: np.ndarray | None = None) -> np.ndarray:
        """σ̂ (M, len(axes)) mm: the PointNet spread head (sets formed as in ``predict``), else the ``spread``
        estimator set on the model (CatBoost RMSEWithUncertainty, see learn/study.py), else 1 (no spread model)."""
        X = np.asarray(X, np.float32)
        est = self.estimator
        if self.kind == "sets" and getattr(est.module_, "head_sigma", None) is not None:
            from .pointnet import sets_by_group

            g = np.zeros(len(X), np.int64) if groups is None else np.asarray(groups)
            idx, real = sets_by_group(g, est.config.set_size, 0)
            _, sig = est.predict_sets_sigma(X[idx])
            out = np.empty((len(X), sig.shape[-1]))
            out[idx[real]] = sig[real]
            return out
        if self.spread is not None:  # CatBoost RMSEWithUncertainty: columns (mean, variance) in µm, µm²
            var = np.asarray(self.spread.predict(X, prediction_type="RMSEWithUncertainty"))[:, 1]
            return (np.sqrt(np.maximum(var, 0.0)) / TARGET_SCALE).reshape(len(X), 1)
        return np.ones((len(X), len(self.axes)))

    def to_onnx(self, n_features: int):
        if self.kind == "sets":
            return export_pointnet(self.estimator.module_, n_features)
        return export_pointwise(self.family, self.estimator, n_features)


def _check_xy(X: np.ndarray, y: np.ndarray, n_axes: int) -> tuple[np.ndarray, np.ndarray]:
    X = np.asarray(X, np.float32)
    y = np.asarray(y, np.float64)
    if X.ndim != 2:
        raise ValueError(f"features must be (M, F), got {X.shape}")
    if len(X) == 0:
        raise ValueError("no training points (the data set has no points for this axis)")
    y = y.reshape(len(X), -1) if y.size == len(X) * n_axes else y
    if y.shape != (len(X), n_axes):
        raise ValueError(f"targets must be ({len(X)}, {n_axes}) mm, got {y.shape}")
    finite = np.all(np.isfinite(X), 1) & np.all(np.isfinite(y), 1)
    if not finite.all():
        raise ValueError(f"{int((~finite).sum())} training rows have non-finite features or targets")
    return X, y


def fit_model(
    family: str,
    X: np.ndarray,
    y: np.ndarray,
    *,
    seed: int = 0,
    profile: str | Profile = "quick",
    axes: tuple[int, ...] | None = None,
    groups: np.ndarray | None = None,
    params: dict | None = None,
    space: dict | None = None,
    threads: int = 1,
    warm_start: Any = None,
) -> FittedModel:
    """Fit ``family`` on X (M, F) and y (M,) mm (or (M, 3) for ``pointnet_multi``).

    params: skip the search and use these hyper-parameters. space: override the family's search space.
    groups: cloud id per row (PointNet sets never mix clouds; its head search folds by cloud).
    warm_start: PointNet families only: a fitted PointNetReg of the same layout to fine-tune (learn/prior.py).
    Raises UnknownFamilyError, or ValueError for empty/bad data or a search space that cannot be sampled.
    """
    check_family(family)
    prof = get_profile(profile)
    multi = family == "pointnet_multi"
    axes = axes if axes is not None else ((0, 1, 2) if multi else (0,))
    X, y2 = _check_xy(X, y, 3 if multi else 1)
    groups = np.zeros(len(X), np.int64) if groups is None else np.asarray(groups)
    t0 = time.perf_counter()
    from threadpoolctl import threadpool_limits

    with threadpool_limits(max(1, threads)):  # BLAS threads: the machine is shared; oversubscription is slower
        if family in POINTWISE_FAMILIES:
            if warm_start is not None:
                raise ValueError(f"{family}: a warm start applies to the PointNet families only")
            est, best, cv = _fit_pointwise(family, X, y2[:, 0] * TARGET_SCALE, seed, prof, params, space, threads)
        else:
            est, best, cv = _fit_pointnet(family, X, y2, groups, seed, prof, params, threads, warm_start)
    return FittedModel(family, tuple(axes), est, best, cv, time.perf_counter() - t0)


def _fit_pointwise(family, X, y_um, seed, prof, params, space, threads):
    est = make_estimator(family, seed, prof, threads)
    if params is not None:
        est.set_params(**params)
        est.fit(X, y_um)
        return est, dict(params), None
    space = search_space(family, prof) if space is None else space
    validate_space(space, family)
    rng = np.random.default_rng(seed)
    sub = rng.choice(len(X), min(len(X), prof.cv_max_points), replace=False)
    folds = min(prof.cv, len(sub))
    if folds < 2:
        raise ValueError(f"{family}: {len(sub)} training points are too few for a {prof.cv}-fold search")
    search = RandomizedSearchCV(est, space, n_iter=prof.n_iter, cv=KFold(folds, shuffle=True, random_state=seed),
                                scoring="neg_mean_absolute_error", random_state=seed, n_jobs=1, refit=False,
                                error_score="raise")
    search.fit(X[sub], y_um[sub])
    best = {k: (v.item() if hasattr(v, "item") else v) for k, v in search.best_params_.items()}
    est.set_params(**best)
    est.fit(X, y_um)
    return est, best, float(-search.best_score_ / TARGET_SCALE)


def _pointnet_config(family: str, prof: Profile, threads: int, head: tuple[int, ...] | None = None,
                     epochs: int | None = None) -> PointNetConfig:
    if family == "pointnet_multi":
        c = dict(prof.compact)
        return PointNetConfig(block1=tuple(c["block1"]), block2=tuple(c["block2"]), head=tuple(head or c["head"]),
                              epochs=epochs or c["epochs"], threads=threads, sigma_head=True)
    return PointNetConfig(block1=STUDY_LAYOUT["block1"], block2=tuple(prof.pointnet_study_block2),
                          head=tuple(head or prof.pointnet_grid[0]), epochs=epochs or prof.pointnet_epochs,
                          threads=threads)


def _fit_pointnet(family, X, y2, groups, seed, prof, params, threads, warm_start=None):
    if warm_start is not None:  # fine-tune the prior: its layout, no head search
        model = PointNetRegressor(_pointnet_config(family, prof, threads), seed, warm_start=warm_start)
        model.fit(X, y2, groups)
        return model, {**model.get_params(), "warm_start": True}, None
    if params is not None and "head" in params:
        head, cv = tuple(params["head"]), None
    elif family == "pointnet" and len(prof.pointnet_grid) > 1:
        # The study's grid search over the final MLP, with CV folded by cloud (3 folds, shorter training).
        n_groups = len(np.unique(groups))
        if n_groups < 3:
            raise ValueError("PointNet head search needs at least 3 clouds")
        scores = {}
        for h in prof.pointnet_grid:
            errs = []
            for tr, va in GroupKFold(3).split(X, y2, groups):
                m = PointNetRegressor(_pointnet_config(family, prof, threads, h, prof.pointnet_grid_epochs), seed)
                m.fit(X[tr], y2[tr], groups[tr])
                errs.append(float(np.mean(np.abs(m.predict(X[va], groups[va]) - y2[va]))))
            scores[h] = float(np.mean(errs))
        head = min(scores, key=lambda k: scores[k])
        cv = scores[head]
    else:
        head, cv = None, None
    model = PointNetRegressor(_pointnet_config(family, prof, threads, head), seed).fit(X, y2, groups)
    return model, model.get_params(), cv


def feature_units(names: list[str]) -> list[str]:
    """Units of the features from the feature registry (empty string where unknown)."""
    try:
        from ..judge.features import REGISTRY
    except ImportError:
        return [""] * len(names)
    units = []
    for n in names:
        try:
            units.append(str(REGISTRY.get(n).unit))
        except (KeyError, ValueError):
            units.append("")
    return units


def export_model_set(
    models: list[FittedModel],
    out_dir: str | Path,
    *,
    feature_names: list[str],
    X_train: np.ndarray | None = None,
    card_extra: dict | None = None,
    model_id: str | None = None,
    check_X: np.ndarray | None = None,
) -> Path:
    """Write ``out_dir/card.json`` and one ONNX file per model; return ``out_dir``.

    The models must cover x, y and z exactly once. X_train gives the domain (training min/max; suggested margin
    5 % of the range) and a 16-row background for SHAP. check_X: rows (one cloud) on which ONNX Runtime must
    reproduce the framework within 1e-5 mm (max difference stored in the card; a larger one raises RuntimeError).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    covered = sorted(a for m in models for a in m.axes)
    if covered != [0, 1, 2]:
        raise ValueError(f"a model set must cover the axes x, y, z exactly once, got {covered}")
    names = list(feature_names)
    card: dict[str, Any] = {
        "format": CARD_FORMAT,
        "id": model_id or "-".join(sorted({m.family for m in models})),
        "feature_names": names,
        "feature_units": feature_units(names),
        "axes": list(AXES),
        "target": "systematic error nominal - measured per axis of the scan frame, mm",
        "models": [],
    }
    set_models = [m for m in models if m.kind == "sets"]
    if set_models:
        card["set_size"] = int(set_models[0].estimator.config.set_size)
        card["partition_seed"] = 0
        card["global_feature"] = GLOBAL_FEATURE_DOC
    if X_train is not None:
        Xt = np.asarray(X_train, np.float64)
        # Raw training min/max; consumers widen it by ``margin`` × range (the node's domain_margin parameter).
        card["domain"] = {"lo": Xt.min(0).tolist(), "hi": Xt.max(0).tolist(), "margin": DOMAIN_MARGIN}
        from .uncertainty import fit_domain

        card["domain_mv"] = fit_domain(Xt)  # the multivariate domain (ModelSet.domain_distance)
        rng = np.random.default_rng(0)
        card["background"] = Xt[rng.choice(len(Xt), min(16, len(Xt)), replace=False)].tolist()
    card.update(card_extra or {})
    protos = []
    for m in models:
        axes = "".join(AXES[a] for a in m.axes)
        fname = f"{m.family}_{axes}.onnx"
        card["models"].append({"family": m.family, "file": fname, "kind": m.kind, "axes": [AXES[a] for a in m.axes],
                               "params": _jsonable(m.params)})
        protos.append((fname, m.to_onnx(len(names))))
    # Hashes are of the final files; compute them by writing with the card (sans hashes) embedded.
    for (fname, proto), entry in zip(protos, card["models"], strict=True):
        data = embed_card(proto, {k: v for k, v in card.items() if k != "models"}).SerializeToString()
        (out / fname).write_bytes(data)
        entry["sha256"] = hashlib.sha256(data).hexdigest()
    if check_X is not None:
        card["onnx_check"] = {"max_abs_diff_mm": _onnx_check(models, out, card, check_X), "tolerance_mm": 1e-5}
    (out / "card.json").write_text(json.dumps(_jsonable(card), indent=1, sort_keys=True))
    return out


def _onnx_check(models: list[FittedModel], out: Path, card: dict, X: np.ndarray) -> float:
    """Max |ONNX Runtime − framework| (mm) over X treated as one cloud; raises if above 1e-5 mm."""
    import onnxruntime as ort

    from .pointnet import partition_sets

    X = np.asarray(X, np.float32)
    worst = 0.0
    for m, entry in zip(models, card["models"], strict=True):
        sess = ort.InferenceSession(str(out / entry["file"]), providers=["CPUExecutionProvider"])
        if m.kind == "sets":
            idx, _ = partition_sets(len(X), card["set_size"], card["partition_seed"])
            outs = sess.run(None, {"X": X[idx]})
            if len(outs) > 1:  # spread head: σ checked too (ONNX log σ against the framework's)
                ref, sig = m.estimator.predict_sets_sigma(X[idx])
                worst = max(worst, float(np.max(np.abs(np.exp(outs[1].astype(np.float64)) - sig))))
            else:
                ref = m.estimator.predict_sets(X[idx])
            got = outs[0]
        else:
            ref = m.predict(X)
            got = sess.run(None, {"X": X})[0]
        worst = max(worst, float(np.max(np.abs(np.asarray(got, np.float64) - ref))))
    if worst > 1e-5:
        raise RuntimeError(f"ONNX Runtime differs from the framework by {worst:.3g} mm (> 1e-5 mm)")
    return worst


def _jsonable(o: Any) -> Any:
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return o
