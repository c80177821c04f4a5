"""The closed loop on a LoopData table: model → residual → trace → add the top effect → before/after, iterated.

Roles of the groups (clouds or profiles), drawn once with the seed:
- ``train`` (A): the model of the current features is fitted here (with a given model: its residual corrector);
- ``trace`` (B): residuals are traced here (group-held-out CV inside B, see trace.py);
- ``eval`` (C): before / after metrics, held out from both tracing and model fitting. Per-identity offsets are
  cross-fitted inside each identity (fit on half of its blocks, applied to the other half), so eval points are
  out of sample for them too.
All errors in mm (nominal − measured), residual = actual − predicted.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .candidates import CandidateInfo, build_candidates
from .correct import cross_fit_offsets, fit_offsets
from .data import LoopData, LoopInputError
from .model import AxisModel, GivenModel, fit_family
from .trace import TraceConfig, trace_candidates

__all__ = ["LoopConfig", "LoopResult", "error_summary", "metrics", "run_loop", "split_roles"]

ROLE_TRAIN, ROLE_TRACE, ROLE_EVAL = 0, 1, 2


@dataclass
class LoopConfig:
    """Loop parameters.

    Attributes:
        family: model family retrained with the current features ("catboost").
        iterations: boosting iterations of the family (per axis).
        max_iter: at most this many effects are added.
        correction: "auto" (identity candidates → per-identity offset, others → feature + retrain),
            "feature" (only continuous candidates may be selected), "offset" (only identity candidates).
        candidates: restrict the trace to these candidate names (None: the whole library).
        fractions: share of groups for train / trace / eval (train ignored with a given model).
        block_size: points per block for the identity hold-out and the offset cross-fit.
        offset_ridge: ridge (relative) of the per-identity offset fit.
        min_gain: a traced effect is added only if it lowers the squared error of the trace part by this fraction
            (the trace part is held out from model fitting; offsets are cross-fitted); else the next one is tried.
        max_tries: at most this many significant candidates of each kind (continuous, identity) are tried per
            iteration (so failing continuous candidates cannot use up the tries of the identity ones).
        trace: TraceConfig (permutations, alpha, minimum effect, ...).
        seed: seed of the role draw, the model and the trace.
    """

    family: str = "catboost"
    iterations: int = 300
    max_iter: int = 3
    correction: str = "auto"
    candidates: list[str] | None = None
    fractions: tuple[float, float, float] = (0.4, 0.3, 0.3)
    block_size: int = 24
    offset_ridge: float = 1e-3
    min_gain: float = 0.02
    max_tries: int = 4
    trace: TraceConfig = field(default_factory=TraceConfig)
    seed: int = 0
    threads: int = 2


@dataclass
class LoopResult:
    """What ``run_loop`` found: the report, the final model and the data it was fitted on."""

    report: dict
    model: AxisModel | None  # the final retrained model (None with a given model or nothing to retrain)
    feature_names: list[str]
    added_features: list[str]
    offsets: list[str]
    plots: list[dict]  # {"iteration", "variable", "x", "before", "after"} arrays on the eval set (for report.py)
    X: np.ndarray | None = None  # final feature matrix (all points)
    train_mask: np.ndarray | None = None  # rows the model (or, with a given model, its corrector) was fitted on


def split_roles(groups: np.ndarray, fractions: tuple[float, float, float], seed: int, need_train: bool) -> np.ndarray:
    """Role per point (0 train, 1 trace, 2 eval), whole groups per role. Needs ≥ 2 trace groups, ≥ 1 eval group
    and (``need_train``) ≥ 1 train group."""
    ug = np.unique(groups)
    need = 4 if need_train else 3
    if len(ug) < need:
        raise LoopInputError(
            f"too few clouds/profiles to hold out: {len(ug)} (need ≥ {need}: "
            f"{'1 to train, ' if need_train else ''}2 to trace, 1 to evaluate)")
    rng = np.random.default_rng(seed)
    perm = ug[rng.permutation(len(ug))]
    f = np.asarray(fractions, dtype=float)
    if not need_train:
        f = np.array([0.0, f[1], f[2]])
    f = f / f.sum()
    n = len(ug)
    n_eval = max(1, round(f[2] * n))
    n_train = max(1, round(f[0] * n)) if need_train else 0
    n_trace = n - n_eval - n_train
    while n_trace < 2:
        if n_train > 1:
            n_train -= 1
        elif n_eval > 1:
            n_eval -= 1
        else:
            break
        n_trace = n - n_eval - n_train
    role_of = {}
    for i, g in enumerate(perm):
        role_of[g] = ROLE_TRAIN if i < n_train else (ROLE_TRACE if i < n_train + n_trace else ROLE_EVAL)
    return np.array([role_of[g] for g in ug])[np.searchsorted(ug, groups)]


def metrics(actual: np.ndarray, pred: np.ndarray, normals: np.ndarray | None = None) -> dict:
    """Per axis (x, y, z; and 'normal' when normals are given): MAE, R², p95 of |actual − pred| (mm)."""
    out: dict[str, dict] = {}
    cols = [(ax, actual[:, i], pred[:, i]) for i, ax in enumerate("xyz")]
    if normals is not None:
        cols.append(("normal", np.einsum("ij,ij->i", actual, normals), np.einsum("ij,ij->i", pred, normals)))
    for ax, a, p in cols:
        r = a - p
        sst = float(((a - a.mean()) ** 2).sum())
        out[ax] = {
            "mae": float(np.abs(r).mean()),
            "r2": float(1.0 - (r**2).sum() / sst) if sst > 0 else 0.0,
            "p95": float(np.quantile(np.abs(r), 0.95)),
            "rmse": float(np.sqrt((r**2).mean())),
        }
    return out


def error_summary(errors: np.ndarray, normals: np.ndarray) -> dict:
    """Step 1: ground-truth error statistics (mm)."""
    en = np.einsum("ij,ij->i", errors, normals)
    d = {ax: {"mean": float(errors[:, i].mean()), "std": float(errors[:, i].std()),
              "p95_abs": float(np.quantile(np.abs(errors[:, i]), 0.95))} for i, ax in enumerate("xyz")}
    d["normal"] = {"mean": float(en.mean()), "std": float(en.std()), "rms": float(np.sqrt((en**2).mean())),
                   "p95_abs": float(np.quantile(np.abs(en), 0.95))}
    return d


def _ordered(scores, info: dict[str, CandidateInfo], correction: str, max_tries: int) -> list:
    """Effects to try, in order: significant *continuous* candidates by score (held out by whole clouds/profiles, so
    they generalise to unseen ones), then significant *identity* candidates by score. Identity candidates are scored
    inside their own groups, which lets them mimic any smooth within-group effect (drift, distortion) — so they come
    last, as the loop's last resort (per-profile / per-pass offsets)."""
    ok = [s for s in scores if s.significant and not s.in_model]
    cont = [s for s in ok if info[s.name].kind != "identity" and correction != "offset"]
    ident = [s for s in ok if info[s.name].kind == "identity" and correction != "feature"]
    return sorted(cont, key=lambda s: -s.score)[:max_tries] + sorted(ident, key=lambda s: -s.score)[:max_tries]


def run_loop(data: LoopData, cfg: LoopConfig | None = None, given: GivenModel | None = None) -> LoopResult:
    """Run the closed loop; see the module docstring. Raises LoopInputError on input it cannot hold out."""
    cfg = cfg or LoopConfig()
    if cfg.correction not in ("auto", "feature", "offset"):
        raise ValueError(f"correction must be auto, feature or offset, got {cfg.correction!r}")
    if given is not None and list(given.feature_names) != list(data.feature_names):
        raise LoopInputError("the given model's features differ from the features computed for the input")
    roles = split_roles(data.group, cfg.fractions, cfg.seed, need_train=True)
    A, B, C = (roles == ROLE_TRAIN), (roles == ROLE_TRACE), (roles == ROLE_EVAL)
    for name, m in (("train", A), ("trace", B), ("eval", C)):
        if m.sum() < 4 * cfg.trace.n_bins:
            raise LoopInputError(f"too few points in the {name} part: {int(m.sum())}")
    cand_vals, cand_info = build_candidates(data, include=cfg.candidates)
    if not cand_vals:
        raise LoopInputError("no candidate variable available for this input")
    E, Nrm = data.errors, data.normals
    feat_names = list(data.feature_names)
    X = np.asarray(data.X, dtype=np.float32)

    def fit_model(Xm: np.ndarray, names: list[str], target: np.ndarray = E):
        return fit_family(cfg.family, Xm[A], target[A], names, seed=cfg.seed, iterations=cfg.iterations,
                          threads=cfg.threads)

    if given is None:
        model: Any = fit_model(X, feat_names)
        base_pred = model.predict(X)
    else:
        model = None
        base_pred = given.predict(X)
    model_pred = base_pred.copy()
    offsets: list[str] = []
    offset_pred = np.zeros_like(model_pred)
    added: list[str] = []
    offset_summaries: dict[str, dict] = {}

    def offsets_for(mpred: np.ndarray, names: list[str]) -> tuple[np.ndarray, dict[str, dict]]:
        """Cross-fitted per-identity offsets (applied in order) on top of ``mpred``, and their eval summaries."""
        total = np.zeros_like(mpred)
        summ: dict[str, dict] = {}
        for name in names:
            res = E - mpred - total
            total += cross_fit_offsets(res, Nrm, cand_vals[name], data.order, cfg.block_size, cfg.offset_ridge)
            uk, w = fit_offsets(res[C], Nrm[C], cand_vals[name][C], cfg.offset_ridge)
            mag = np.linalg.norm(w, axis=1) * 1e3
            summ[name] = {"n_identities_eval": len(uk), "median_um": float(np.median(mag)),
                          "max_um": float(mag.max())}
        return total, summ

    report: dict = {
        "schema": "xmetro.loop.report/1",
        "source": data.source,
        "hold_by": data.hold_by,
        "artifact": data.artifact,
        "n_points": int(data.n),
        "n_groups": len(data.groups),
        "roles": {r: {"groups": sorted(data.group_names[g] if g < len(data.group_names) else str(g)
                                       for g in np.unique(data.group[roles == k])),
                      "n_points": int((roles == k).sum())}
                  for r, k in (("train", ROLE_TRAIN), ("trace", ROLE_TRACE), ("eval", ROLE_EVAL))},
        "model": {"kind": "given" if given is not None else "retrained", "family": cfg.family if given is None else
                  getattr(given.model_set, "id", "given"), "features": list(feat_names)},
        "ground_truth": {"all": error_summary(E, Nrm), "eval": error_summary(E[C], Nrm[C])},
        "config": {"family": cfg.family, "iterations": cfg.iterations,
                   "max_iter": cfg.max_iter, "min_gain": cfg.min_gain,
                   "max_tries": cfg.max_tries, "correction": cfg.correction, "seed": cfg.seed,
                   "block_size": cfg.block_size, "trace": {k: getattr(cfg.trace, k) for k in
                                                           ("n_folds", "n_bins", "shrink", "n_perm", "alpha",
                                                            "min_effect", "block_size", "max_points")}},
    }
    before = metrics(E[C], model_pred[C], Nrm[C])
    iterations: list[dict] = []
    plots: list[dict] = []
    first_candidates: list[dict] | None = None
    for it in range(1, cfg.max_iter + 1):
        pred = model_pred + offset_pred
        resid = E - pred
        rn = np.einsum("ij,ij->i", resid, Nrm)
        names = [n for n in cand_vals if n not in added and n not in offsets]
        tcfg = TraceConfig(**{**cfg.trace.__dict__, "seed": cfg.trace.seed + it})
        scores = trace_candidates(
            resid[B], {n: cand_vals[n][B] for n in names}, {n: cand_info[n].kind for n in names},
            data.group[B], data.order[B], tcfg, normal_residual=rn[B],
            meta={n: {"description": cand_info[n].description, "unit": cand_info[n].unit,
                      "in_model": cand_info[n].in_model} for n in names},
        )
        cands = [s.to_dict() for s in scores]
        if first_candidates is None:
            first_candidates = cands
        rec: dict = {"iteration": it, "candidates": cands, "selected": None, "rejected": [],
                     "before": metrics(E[C], pred[C], Nrm[C])}
        mse_b = float(((E[B] - pred[B]) ** 2).sum())
        sel = None
        for cand in _ordered(scores, cand_info, cfg.correction, cfg.max_tries):
            kind = cand_info[cand.name].kind
            if kind == "identity":
                t_offsets = [*offsets, cand.name]
                t_model, t_model_pred, t_X, t_feats = model, model_pred, X, feat_names
            else:
                t_offsets = offsets
                t_X = np.hstack([X, cand_vals[cand.name][:, None].astype(np.float32)])
                t_feats = [*feat_names, cand.name]
                # The model (or the given model's residual corrector) learns what the offsets already added leave
                # (their current values, then refitted on top below): otherwise it is trained on the per-identity
                # offsets too, which no feature can carry to unseen profiles or passes.
                if given is None:
                    t_model = fit_model(t_X, t_feats, E - offset_pred)
                    t_model_pred = t_model.predict(t_X)
                else:
                    t_model = model
                    corr = fit_model(t_X, t_feats, E - base_pred - offset_pred)
                    t_model_pred = base_pred + corr.predict(t_X)
            t_offset_pred, t_summ = offsets_for(t_model_pred, t_offsets)
            t_pred = t_model_pred + t_offset_pred
            # Check on the trace part (held out from model fitting; offsets cross-fitted): a traced variable that
            # does not lower the error there is not added (e.g. a within-profile shape no model can generalise).
            gain = 1.0 - float(((E[B] - t_pred[B]) ** 2).sum()) / mse_b
            if gain < cfg.min_gain:
                rec["rejected"].append({"name": cand.name, "trace_gain": gain})
                continue
            sel, model, model_pred, X, feat_names = cand, t_model, t_model_pred, t_X, t_feats
            offsets, offset_pred = t_offsets, t_offset_pred
            offset_summaries.update(t_summ)
            if kind == "identity":
                action = {"correction": "offset", "variable": cand.name, "offsets": t_summ[cand.name]}
            else:
                added.append(cand.name)
                action = {"correction": "feature", "variable": cand.name, "feature": cand.name}
            rec["selected"] = {**cand.to_dict(), **action, "trace_gain": gain}
            break
        if sel is None:
            rec["after"] = rec["before"]
            iterations.append(rec)
            break
        new_pred = model_pred + offset_pred
        rec["after"] = metrics(E[C], new_pred[C], Nrm[C])
        iterations.append(rec)
        plots.append({"iteration": it, "variable": sel.name, "x": cand_vals[sel.name][C],
                      "before": rn[C], "after": np.einsum("ij,ij->i", E[C] - new_pred[C], Nrm[C]),
                      "unit": cand_info[sel.name].unit})
    final_pred = model_pred + offset_pred
    report["candidates"] = first_candidates or []
    report["selected"] = iterations[0]["selected"] if iterations and iterations[0]["selected"] else None
    report["added"] = {"features": added, "offsets": offsets, "offset_summaries": offset_summaries}
    report["before"] = before
    report["after"] = metrics(E[C], final_pred[C], Nrm[C])
    report["iterations"] = iterations
    report["final_features"] = feat_names
    fit_rows = A
    return LoopResult(report, model if (given is None and added) else None, feat_names, added, offsets, plots, X,
                      fit_rows)
