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

from .candidates import SPECTRAL_NAMES, CandidateInfo, build_candidates
from .correct import cross_fit_offsets, fit_offsets
from .data import LoopData, LoopInputError
from .diagnose import FIXES, LOCKED_COHERENCE, fix_for, offset_table, oscillation_finding
from .model import AxisModel, GivenModel, fit_family, fit_normal_corrector
from .periodic import PERIODIC_NAMES, fit_periodic, frequency_grid, periodic_gain, transfer_compare
from .trace import TraceConfig, cv_folds, heldout_gain, holm, spans_groups, spectral_test, trace_candidates

__all__ = ["LoopConfig", "LoopResult", "error_summary", "metrics", "run_loop", "split_roles", "trace_gain_um"]

ROLE_TRAIN, ROLE_TRACE, ROLE_EVAL = 0, 1, 2
REPORT_SCHEMA = "xmetro.loop.report/2"


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
        confirm_z: a traced effect is added only if, refitted, it lowers the mean squared residual along the normal
            of the trace groups (held out from model fitting; offsets cross-fitted) by at least
            ``trace.min_size_um``² and by ``confirm_z`` standard errors over those groups (``trace.heldout_gain``;
            or by ``min_gain`` of its squared error with that size); else the next one is tried.
        min_gain: see ``confirm_z``.
        max_tries: at most this many significant candidates of each kind (continuous, identity) are tried per
            iteration (so failing continuous candidates cannot use up the tries of the identity ones).
        min_phase_coherence: a candidate significant by the spectral test only is tried as a feature when the
            oscillation's phase coherence across clouds reaches this; else it is a diagnostic oscillation.
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
    confirm_z: float = 1.0
    min_gain: float = 0.02
    max_tries: int = 4
    min_phase_coherence: float = LOCKED_COHERENCE
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


def split_roles(groups: np.ndarray, fractions: tuple[float, float, float], seed: int, need_train: bool,
                units: np.ndarray | None = None) -> np.ndarray:
    """Role per point (0 train, 1 trace, 2 eval), whole groups per role. Needs ≥ 2 trace groups, ≥ 1 eval group
    and (``need_train``) ≥ 1 train group. ``units`` (per point): groups that share a unit share a role — the
    repeats of one sensor position (profile data's ``pose``) then never straddle training and evaluation, and a
    role holds all the repeats the identity tests need."""
    if units is not None:
        u = np.asarray(units, dtype=float)
        if len(np.unique(u)) >= (4 if need_train else 3):
            _, ui = np.unique(u, return_inverse=True)
            return split_roles(ui.reshape(-1), fractions, seed, need_train)
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


def trace_gain_um(res_before: np.ndarray, res_after: np.ndarray, normals: np.ndarray, groups: np.ndarray,
                  cfg: LoopConfig) -> dict:
    """Gain in µm of a refitted correction on the trace groups (``trace.heldout_gain`` on the residual along the
    normal, per group), with ``cfg.confirm_z`` as the uncertainty factor."""
    rb = np.einsum("ij,ij->i", res_before, normals)
    ra = np.einsum("ij,ij->i", res_after, normals)
    _, g = np.unique(groups, return_inverse=True)
    g = g.reshape(-1)
    tc = TraceConfig(**{**cfg.trace.__dict__, "gain_z": cfg.confirm_z})
    return heldout_gain(np.bincount(g, rb**2), np.bincount(g, ra**2), np.bincount(g, np.abs(rb)),
                        np.bincount(g, np.abs(ra)), np.bincount(g).astype(float), tc)


def _spectral_only(s) -> bool:
    return bool(s.spectral and s.spectral.get("significant") and "learner" not in s.significant_by)


def _ordered(scores, info: dict[str, CandidateInfo], correction: str, max_tries: int,
             min_coherence: float = 0.5) -> list:
    """Effects to try, in order: significant *continuous* candidates by held-out gain in µm² (held out by whole
    clouds/profiles, so they generalise to unseen ones), then significant *identity* candidates by score. Identity
    candidates are scored inside their own groups, which lets them mimic any smooth within-group effect (drift,
    distortion) — so they come last, as the loop's last resort (per-profile / per-pass offsets). A candidate
    significant by the spectral test alone is tried as a feature only when its oscillation is phase-locked to it
    (coherence ≥ ``min_coherence``): a feature cannot predict an oscillation whose phase changes from cloud to
    cloud (it is diagnostic)."""
    ok = [s for s in scores if s.significant and not s.in_model and not info[s.name].confounded
          and not (_spectral_only(s) and s.spectral["phase_coherence"] < min_coherence)]
    cont = [s for s in ok if info[s.name].kind != "identity" and correction != "offset"]
    ident = [s for s in ok if info[s.name].kind == "identity" and correction != "feature"]
    # Continuous candidates by their held-out gain in µm² (on unseen groups), identities by their score.
    return (sorted(cont, key=lambda s: -(s.gain["mse_um2"] if s.gain else s.rank_score))[:max_tries]
            + sorted(ident, key=lambda s: -s.score)[:max_tries])


def run_loop(data: LoopData, cfg: LoopConfig | None = None, given: GivenModel | None = None) -> LoopResult:
    """Run the closed loop; see the module docstring. Raises LoopInputError on input it cannot hold out."""
    cfg = cfg or LoopConfig()
    if cfg.correction not in ("auto", "feature", "offset"):
        raise ValueError(f"correction must be auto, feature or offset, got {cfg.correction!r}")
    if given is not None and list(given.feature_names) != list(data.feature_names):
        raise LoopInputError("the given model's features differ from the features computed for the input")
    units = data.fields.get("pose") if data.hold_by == "profile" else None
    roles = split_roles(data.group, cfg.fractions, cfg.seed, need_train=True, units=units)
    A, B, C = (roles == ROLE_TRAIN), (roles == ROLE_TRACE), (roles == ROLE_EVAL)
    for name, m in (("train", A), ("trace", B), ("eval", C)):
        if m.sum() < 4 * cfg.trace.n_bins:
            raise LoopInputError(f"too few points in the {name} part: {int(m.sum())}")
    cand_vals, cand_info = build_candidates(data, include=cfg.candidates)
    if not cand_vals:
        raise LoopInputError("no candidate variable available for this input")
    E, Nrm = data.errors, data.normals
    feat_names = list(data.feature_names)
    n_given = len(feat_names)
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
    per_pred = np.zeros_like(model_pred)  # phase-locked periodic corrections of scan time (along the normal)
    periodic_fits: dict[str, dict] = {}
    # Rows whose residual is out of sample for the model: the trace part, and the train part too with a given model
    # (fitted elsewhere); the periodic transfer test holds out whole groups among them.
    T = (A | B) if given is not None else B

    def refit(Xm: np.ndarray, names: list[str], o_pred: np.ndarray) -> tuple[Any, np.ndarray]:
        """The model of the features ``names`` (or the given model's corrector) fitted to what the offsets
        ``o_pred`` leave: trained on the per-identity offsets too, it would learn them from whatever feature tells
        the training clouds apart, and no feature carries them to unseen profiles or passes."""
        if given is None:
            m = fit_model(Xm, names, E - o_pred - per_pred)
            return m, m.predict(Xm) + per_pred
        # The given model covers its own features; the corrector learns what they leave along the normal as a
        # function of the added variables only. On the full feature set, per axis, it fits the few training
        # clouds' geometry and misses e.g. a many-period oscillation over t (docs/closed-loop.md).
        new_cols = Xm[:, n_given:]
        cols = [i for i, nm in enumerate(names[n_given:]) if nm not in periodic_fits]
        if not cols:
            return model, base_pred + per_pred
        rn_target = np.einsum("ij,ij->i", E - base_pred - per_pred - o_pred, Nrm)
        corr = fit_normal_corrector(cfg.family, new_cols[A][:, cols], rn_target[A],
                                    [names[n_given + i] for i in cols], seed=cfg.seed, iterations=cfg.iterations,
                                    threads=cfg.threads)
        return model, base_pred + per_pred + corr.predict(new_cols[:, cols], Nrm)

    def offsets_for(mpred: np.ndarray, names: list[str]) -> tuple[np.ndarray, dict[str, dict]]:
        """Cross-fitted per-identity offsets (applied in order) on top of ``mpred``, and their eval summaries."""
        total = np.zeros_like(mpred)
        summ: dict[str, dict] = {}
        for name in names:
            res = E - mpred - total
            shared = spans_groups(cand_vals[name], data.group)  # repeats share it: fit on some, apply to others
            total += cross_fit_offsets(res, Nrm, cand_vals[name], data.order, cfg.block_size, cfg.offset_ridge,
                                       groups=data.group if shared else None)
            uk, w = fit_offsets(res[C], Nrm[C], cand_vals[name][C], cfg.offset_ridge)
            mag = np.linalg.norm(w, axis=1) * 1e3
            summ[name] = {"n_identities_eval": len(uk), "median_um": float(np.median(mag)),
                          "max_um": float(mag.max())}
        return total, summ

    report: dict = {
        "schema": REPORT_SCHEMA,
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
                   "max_iter": cfg.max_iter, "confirm_z": cfg.confirm_z,
                   "min_gain": cfg.min_gain,
                   "max_tries": cfg.max_tries, "correction": cfg.correction, "seed": cfg.seed,
                   "block_size": cfg.block_size, "trace": {k: getattr(cfg.trace, k) for k in
                                                           ("n_folds", "n_bins", "bin_levels", "shrink", "n_perm",
                                                            "alpha", "min_effect", "min_size_um", "gain_z",
                                                            "gain_levels",
                                                            "block_size", "max_points",
                                                            "spectral", "spectral_min_periods",
                                                            "spectral_max_periods", "spectral_n_freq",
                                                            "spectral_detrend")}},
    }
    before = metrics(E[C], model_pred[C], Nrm[C])
    iterations: list[dict] = []
    plots: list[dict] = []
    first_candidates: list[dict] | None = None
    oscillations: dict[str, dict] = {}
    diag_gain: dict[str, dict] = {}
    pred_steps: list[dict] = []
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
            spectral=SPECTRAL_NAMES.intersection(names),
        )
        cands = [{**s.to_dict(), "confounded": cand_info[s.name].confounded,
                  "finding": "diagnostic" if cand_info[s.name].kind == "identity" else "predictive"} for s in scores]
        if first_candidates is None:
            first_candidates = cands
        rec: dict = {"iteration": it, "candidates": cands, "selected": None, "rejected": [],
                     "before": metrics(E[C], pred[C], Nrm[C])}
        mse_b = float(((E[B] - pred[B]) ** 2).sum())
        sel = None
        it_osc: dict[str, dict] = {}  # oscillations a feature cannot follow, seen in this iteration
        for s_ in scores:
            if (_spectral_only(s_) and not s_.in_model and not cand_info[s_.name].confounded
                    and s_.spectral is not None and s_.spectral["phase_coherence"] < cfg.min_phase_coherence):
                it_osc[s_.name] = oscillation_finding(s_.to_dict(), s_.name, cand_info[s_.name].unit, None)
        transfer = (_transfer_tests(rn, T, names, cand_info, cand_vals, data, cfg,
                                     "train+trace" if given is not None else "trace")
                    if cfg.correction != "offset" else {})
        rec["transfer"] = transfer
        ordered = _ordered(scores, cand_info, cfg.correction, cfg.max_tries, cfg.min_phase_coherence)
        n_cont = sum(cand_info[c_.name].kind != "identity" for c_ in ordered)
        # Continuous candidates as features first, then a phase-locked periodic correction of scan time when it
        # transfers to held-out clouds (None below), then identities (diagnostic offsets) as the last resort.
        for cand in [*ordered[:n_cont], None, *ordered[n_cont:]]:
            if cand is None:
                done = False
                for name_, tr_ in transfer.items():
                    if tr_["transfers"] != "periodic" or name_ in added:
                        continue
                    fit = fit_periodic(rn[T], cand_vals[name_][T], data.group[T],
                                       frequency_grid(cand_vals[name_][T], data.group[T]))
                    if fit is None:
                        continue
                    sc_ = next(s_ for s_ in scores if s_.name == name_)
                    corr_ = fit.predict(cand_vals[name_])[:, None] * Nrm
                    per_pred = per_pred + corr_
                    model_pred = model_pred + corr_
                    periodic_fits[name_] = fit.to_dict(cand_info[name_].unit or "s")
                    X = np.hstack([X, cand_vals[name_][:, None].astype(np.float32)])
                    feat_names = [*feat_names, name_]
                    added.append(name_)
                    sel = sc_
                    g_ = tr_["periodic"]
                    pred_steps.append({"iteration": it, "variable": name_, "correction": "periodic",
                                       "trace_gain_um": g_, "heldout_gain": g_, "score": sc_.score,
                                       "p_holm": sc_.p_holm, "significant_by": ["transfer"],
                                       "periodic": periodic_fits[name_], "spectral": sc_.spectral,
                                       "after": metrics(E[C], model_pred[C], Nrm[C])})
                    rec["selected"] = {**sc_.to_dict(), "correction": "periodic", "variable": name_,
                                       "feature": name_, "finding": "predictive", "significant_by": ["transfer"],
                                       "periodic": periodic_fits[name_], "trace_gain_um": g_, "trace_gain": None}
                    done = True
                    break
                if done:
                    break
                continue
            kind = cand_info[cand.name].kind
            if kind == "identity":
                t_offsets = [*offsets, cand.name]
                t_model, t_model_pred, t_X, t_feats = model, model_pred, X, feat_names
                if added:
                    # The features already added learnt these offsets too (they were not in yet): refit them on
                    # what the offsets leave (on top of the current model, or of the model without the added
                    # features), then the offsets on top (below). Kept: whichever of the current model and the two
                    # refits predicts the trace part best *live* (without offsets; the trace part is held out from
                    # fitting): a diagnostic offset must never make the live model worse.
                    options = [(model, model_pred)]
                    for start in (model_pred, base_pred):
                        options.append(refit(X, feat_names, offsets_for(start, t_offsets)[0]))
                    live = [float(((E[B] - p_[B]) ** 2).sum()) for _, p_ in options]
                    t_model, t_model_pred = options[int(np.argmin(live))]
            else:
                t_offsets = offsets
                t_X = np.hstack([X, cand_vals[cand.name][:, None].astype(np.float32)])
                t_feats = [*feat_names, cand.name]
                t_model, t_model_pred = refit(t_X, t_feats, offset_pred)
            t_offset_pred, t_summ = offsets_for(t_model_pred, t_offsets)
            t_pred = t_model_pred + t_offset_pred
            # Check on the trace part (held out from model fitting; offsets cross-fitted): a traced variable that
            # does not lower the error there is not added (e.g. a within-profile shape no model can generalise).
            gain = 1.0 - float(((E[B] - t_pred[B]) ** 2).sum()) / mse_b
            gain_um = trace_gain_um(E[B] - pred[B], E[B] - t_pred[B], Nrm[B], data.group[B], cfg)
            # Kept when its gain in µm on the trace groups exceeds the size floor and confirm_z s.e. — or, a large
            # effect seen on few groups (s.e. poorly known), when it also lowers the trace part's squared error by
            # ≥ min_gain with the same size.
            if not (gain_um["passes"] or (gain >= cfg.min_gain and gain_um["size_um"] >= cfg.trace.min_size_um)):
                rec["rejected"].append({"name": cand.name, "trace_gain": gain, "trace_gain_um": gain_um})
                sp = cand.spectral or {}
                if kind != "identity" and sp.get("significant"):
                    # Significant oscillation the variable cannot predict: diagnostic (confirmed at the end).
                    it_osc[cand.name] = oscillation_finding(cand.to_dict(), cand.name, cand_info[cand.name].unit,
                                                            gain)
                continue
            sel, model, model_pred, X, feat_names = cand, t_model, t_model_pred, t_X, t_feats
            offsets, offset_pred = t_offsets, t_offset_pred
            offset_summaries.update(t_summ)
            if kind == "identity":
                action = {"correction": "offset", "variable": cand.name, "offsets": t_summ[cand.name],
                          "finding": "diagnostic"}
                diag_gain[cand.name] = {"iteration": it, "trace_gain": gain, "trace_gain_um": gain_um,
                                        "score": cand.score, "p_holm": cand.p_holm}
            else:
                added.append(cand.name)
                action = {"correction": "feature", "variable": cand.name, "feature": cand.name,
                          "finding": "predictive"}
                pred_steps.append({"iteration": it, "variable": cand.name, "trace_gain": gain,
                                   "trace_gain_um": gain_um, "heldout_gain": cand.gain, "score": cand.score,
                                   "p_holm": cand.p_holm,
                                   "significant_by": list(cand.significant_by), "spectral": cand.spectral,
                                   "after": metrics(E[C], t_model_pred[C], Nrm[C])})
            rec["selected"] = {**cand.to_dict(), **action, "trace_gain": gain, "trace_gain_um": gain_um}
            break
        if sel is None or cand_info[sel.name].kind == "identity":
            # Only where no feature was added: an oscillation seen before a feature took it is not a finding.
            for k_, v_ in it_osc.items():
                oscillations.setdefault(k_, v_)
        if sel is None:
            rec["after"] = rec["before"]
            rec["after_live"] = metrics(E[C], model_pred[C], Nrm[C])
            iterations.append(rec)
            break
        new_pred = model_pred + offset_pred
        rec["after"] = metrics(E[C], new_pred[C], Nrm[C])
        # What a live node would get (no per-identity offsets: they need the scan's ground truth).
        rec["after_live"] = metrics(E[C], model_pred[C], Nrm[C])
        iterations.append(rec)
        plots.append({"iteration": it, "variable": sel.name, "x": cand_vals[sel.name][C],
                      "before": rn[C], "after": np.einsum("ij,ij->i", E[C] - new_pred[C], Nrm[C]),
                      "unit": cand_info[sel.name].unit})
    final_pred = model_pred + offset_pred
    report["candidates"] = first_candidates or []
    # The first *predictive* effect (a feature a live node computes); diagnostic offsets are never "selected".
    report["selected"] = next((it["selected"] for it in iterations
                               if it["selected"] and it["selected"]["finding"] == "predictive"), None)
    report["added"] = {"features": added, "offsets": offsets, "offset_summaries": offset_summaries}
    live_after = metrics(E[C], model_pred[C], Nrm[C])
    report["before"] = before
    report["after"] = live_after
    report["predictive"] = {
        "added": list(added), "before": before, "after": live_after, "steps": pred_steps,
        "note": "live figures: the model with the added features on held-out eval groups, no ground truth used",
    }
    report["diagnostic"] = _diagnostics(
        data, cand_info, cand_vals, E - model_pred, offsets, diag_gain,
        _confirm_oscillations(oscillations, E - model_pred, offsets, cand_vals, B, data, cfg),
        first_candidates or [],
        metrics(E[C], final_pred[C], Nrm[C]) if offsets else None, cfg)
    report["iterations"] = iterations
    report["final_features"] = feat_names
    fit_rows = A
    report["predictive"]["periodic"] = periodic_fits
    # A periodic correction is not part of the retrained family: the exported model is the family retrained on the
    # augmented features (as with a given model).
    return LoopResult(report, model if (given is None and added and not periodic_fits) else None, feat_names, added,
                      offsets, plots, X, fit_rows)


def _transfer_tests(
    rn: np.ndarray, T: np.ndarray, names: list[str], info: dict[str, CandidateInfo], vals: dict[str, np.ndarray],
    data: LoopData, cfg: LoopConfig, rows: str,
) -> dict[str, dict]:
    """For each candidate of scan time (``PERIODIC_NAMES``): a phase-locked sinusoid of it against per-profile
    offsets, by their gain in µm on clouds they were not fitted on (``periodic.transfer_compare``; rows ``T``,
    subsampled to ``trace.max_points``, folds of whole groups)."""
    out: dict[str, dict] = {}
    todo = [n for n in names if n in PERIODIC_NAMES and not info[n].in_model and not info[n].confounded]
    if not todo:
        return out
    idx = np.flatnonzero(T)
    if len(np.unique(data.group[idx])) < 3:
        return out
    tc = cfg.trace
    rng = np.random.default_rng([cfg.seed, 11])
    if len(idx) > tc.max_points:
        idx = np.sort(rng.choice(idx, tc.max_points, replace=False))
    folds = cv_folds(data.group[idx], data.order[idx], tc.n_folds, by="group", block_size=tc.block_size,
                     seed=tc.seed)
    for name in todo:
        t = vals[name][idx]
        if "line" in data.fields and data.hold_by == "cloud":
            res = transfer_compare(rn[idx], t, data.fields["line"][idx], data.group[idx], folds, tc)
        else:
            per = periodic_gain(rn[idx], t, data.group[idx], folds, tc)
            res = {"periodic": per, "profile_offsets_by_index": None, "profile_offsets_within_recording": None,
                   "transfers": "periodic" if per and per["passes"] else "neither"}
        if res["periodic"] is not None:
            out[name] = {**res, "rows": rows}
    return out


def _diagnostics(
    data: LoopData, info: dict[str, CandidateInfo], vals: dict[str, np.ndarray], live_residual: np.ndarray,
    offsets: list[str], gains: dict[str, dict], oscillations: dict[str, dict], first: list[dict],
    with_offsets: dict | None, cfg: LoopConfig,
) -> dict:
    """The diagnostic section: per-identity offsets (size with bootstrap uncertainty, structure, fix), oscillations
    a feature could not follow, candidates barred by fitted positions. Offsets are refitted in order on what the
    live model leaves (all groups), each on top of the previous ones."""
    findings: list[dict] = []
    res = live_residual.copy()
    for name in offsets:
        keys = vals[name]
        fname = name[len("field_"):] if name.startswith("field_") else ""
        if name == "profile_identity" and data.hold_by != "profile" and "line" in data.fields:
            fname = "line"  # a profile of a scan is (scan, line)
        raw = np.asarray(data.fields[fname], dtype=float) if fname in data.fields else None
        table = offset_table(res, data.normals, keys, data.order, data.group, data.group_names, raw=raw,
                             field=fname, block_size=cfg.block_size, ridge=cfg.offset_ridge, seed=cfg.seed)
        res = res - cross_fit_offsets(res, data.normals, keys, data.order, cfg.block_size, cfg.offset_ridge)
        structure, fix = fix_for(name, data.hold_by)
        findings.append({"variable": name, "kind": "offset", "structure": structure, **gains.get(name, {}),
                         "offsets": table, "needs_ground_truth": True, "fix": fix})
    findings += list(oscillations.values())
    found = {f["variable"] for f in findings}
    also = [{"variable": c["name"], "score": c["score"], "p_holm": c["p_holm"],
             "reason": "significant identity not added (an earlier offset took its share, or it failed the "
                       "trace-part check)"}
            for c in first if c["significant"] and c["kind"] == "identity" and c["name"] not in found]
    barred = [{"variable": c["name"], "score": c["score"], "p_holm": c["p_holm"], "reason": c["confounded"]}
              for c in first if c.get("confounded") and c["significant"]]
    return {"findings": findings, "other_significant_identities": also, "barred_by_fitted_positions": barred,
            "eval_with_offsets": with_offsets,
            "note": "needs the ground truth of the scan it corrects: never a live improvement; eval_with_offsets "
                    "uses offsets cross-fitted on the eval groups' own ground truth"}


def _confirm_oscillations(
    found: dict[str, dict], live_residual: np.ndarray, offsets: list[str], vals: dict[str, np.ndarray],
    B: np.ndarray, data: LoopData, cfg: LoopConfig,
) -> dict[str, dict]:
    """Oscillations a feature could not follow, re-tested at the end on what the live model leaves (trace part)
    minus the offsets of the identities inside which the variable varies: a per-pass step also has spectral power
    over t and positions until its offsets are in. Offsets of identities inside which the variable is constant
    (a profile has one t) are not taken out: they are a function of the variable, and would hide the oscillation
    they sample. Holm over the re-tested ones; the strongest is the finding, the others (the same oscillation
    seen through a variable proportional to it, e.g. scan position ∝ t) are listed with it."""
    if not found:
        return {}
    tc = cfg.trace
    folds = cv_folds(data.group[B], data.order[B], tc.n_folds, by="group", block_size=tc.block_size, seed=tc.seed)
    tests = {}
    for i, name in enumerate(found):
        x = vals[name]
        res = live_residual.copy()
        for ident in offsets:
            keys = vals[ident]
            _, inv = np.unique(keys, return_inverse=True)
            inv = inv.reshape(-1)
            cnt = np.maximum(np.bincount(inv), 1)
            within = float(((x - (np.bincount(inv, x) / cnt)[inv]) ** 2).mean())
            if within < 0.01 * float(x.var()):
                continue  # the variable is (nearly) constant in each identity
            res -= cross_fit_offsets(res, data.normals, keys, data.order, cfg.block_size, cfg.offset_ridge)
        t = spectral_test(res[B], x[B], data.group[B], folds, tc, np.random.default_rng([tc.seed, i, 7]))
        if t is not None:
            tests[name] = t
    if not tests:
        return {}
    adj = holm(np.array([t["p_value"] for t in tests.values()]))
    keep = []
    for (name, t), pa in zip(tests.items(), adj, strict=True):
        if pa <= tc.alpha and t["score"] >= tc.min_effect:
            f = dict(found[name])
            if (t["phase_coherence"] >= LOCKED_COHERENCE) != (f["phase_coherence"] >= LOCKED_COHERENCE):
                f["fix"] = FIXES["periodic" if t["phase_coherence"] >= LOCKED_COHERENCE else "oscillation"]
            f.update({"peak_frequency": t["peak_frequency"], "period": t["period"],
                      "amplitude_um": 1e3 * t["amplitude_mm"], "phase_coherence": t["phase_coherence"],
                      "spectral_score": t["score"], "p_holm": float(pa)})
            keep.append(f)
    if not keep:
        return {}
    keep.sort(key=lambda f: -f["spectral_score"])
    head = keep[0]
    head["also_seen_over"] = [{k: f[k] for k in ("variable", "peak_frequency", "unit", "spectral_score")}
                              for f in keep[1:]]
    return {head["variable"]: head}
