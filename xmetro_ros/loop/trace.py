"""Trace a residual to candidate variables: held-out explained variance of a small non-linear regressor + a
permutation test with Holm multiple-testing control.

Method (per candidate variable ``x``, residual ``R`` (N, 3) mm = actual − predicted error):

- Regressor: a shrunken bin-mean (piecewise-constant) fit of ``R`` on ``x``: quantile bins of ``x`` (continuous
  candidates, at every resolution of ``bin_levels``: 16 bins follow a trend, 64-192 an oscillation of many periods;
  the best resolution is kept and the null pays for the choice) or one bin per identity value (identity
  candidates, e.g. a profile or pass id). Piecewise-constant fits catch non-linear and non-monotonic effects;
  shrinkage (``n / (n + shrink)``) keeps sparse bins near zero.
- Spectral test (``spectral_test``, for time / position candidates): phase-free per-cloud periodogram of the
  detrended residual, peak frequency chosen on the other clouds and read on the held-out ones; reports the peak
  frequency, amplitude and phase coherence across clouds.
- Held-out score: K-fold cross-validation. Continuous candidates: folds hold out whole groups (clouds or
  profiles). Identity candidates (an identity's effect cannot transfer to an unseen identity): held out by interleaved
  blocks of points inside each group (fit on some blocks of a profile, score on the others); an identity whose
  values span groups (the sensor position shared by repeated profiles) by whole groups, like continuous ones (fit on
  some repeats, score on the others; a value seen in no training fold predicts 0).
  ``score`` = 1 − SSE / SST over the held-out points and the three axes (the fraction of the residual's variance
  explained out of sample; ≤ 0 when the candidate explains nothing).
- Significance: the same score with the residual rows permuted inside each training fold (``n_perm`` times; the
  held-out residual stays untouched), p = (1 + #{null ≥ observed}) / (1 + n_perm); when no permutation reaches the
  observed score, p is extrapolated from a normal fit to the null scores (capped at 1 / (1 + n_perm)), so that few
  permutations suffice; Holm's step-down correction over every test made (all candidates' learner tests and the
  spectral tests) controls the family-wise error rate.
- A candidate is *significant* when its Holm-adjusted p ≤ ``alpha`` **and** it is big enough: a continuous
  candidate by its held-out gain in µm on the groups it was not fitted on (``heldout_gain``: the drop of the
  mean squared residual along the normal, per held-out group, ≥ ``min_size_um``² and ≥ ``gain_z`` standard errors
  over the groups; the best resolution of ``gain_levels``, against the training groups' mean); an identity
  candidate (diagnostic, scored inside its own groups) by its share of the residual (score ≥ ``min_effect``).
  The point-wise null cannot see cloud-level coincidences (with few clouds, a candidate whose range differs between
  clouds can "explain" per-cloud offsets); the loop therefore also checks that an added effect lowers the error of
  the trace part after refitting (``run.LoopConfig.confirm_z``).

Everything is vectorised over points and permutations (``np.bincount``), no per-point Python loops.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from scipy.stats import norm
from scipy.stats import t as student_t

__all__ = ["CandidateScore", "TraceConfig", "bin_codes", "cv_folds", "heldout_gain", "holm", "spans_groups",
           "spectral_test", "trace_candidates"]


@dataclass(frozen=True)
class TraceConfig:
    """Parameters of the trace (see module docstring)."""

    n_folds: int = 4
    n_bins: int = 16
    bin_levels: tuple[int, ...] = (16, 64, 192)
    shrink: float = 20.0
    n_perm: int = 199
    alpha: float = 0.01
    min_effect: float = 0.05
    min_size_um: float = 0.5
    gain_z: float = 2.0
    gain_levels: tuple[int, ...] = (4, 8, 16, 64)
    block_size: int = 24
    max_points: int = 40000
    seed: int = 0
    spectral: bool = True
    spectral_min_periods: float = 2.0
    spectral_max_periods: float = 64.0
    spectral_n_freq: int = 192
    spectral_detrend: int = 3


@dataclass
class CandidateScore:
    """Result for one candidate. ``score`` and ``score_axes`` are held-out explained-variance fractions."""

    name: str
    kind: str
    score: float
    score_axes: dict[str, float]
    score_normal: float
    p_value: float
    p_holm: float = 1.0
    significant: bool = False
    in_model: bool = False
    description: str = ""
    unit: str = ""
    null_mean: float = 0.0
    null_p95: float = 0.0
    extra: dict = field(default_factory=dict)
    #: spectral test over this candidate (see ``spectral_test``) with its own ``p_holm`` / ``significant``, or None
    spectral: dict | None = None
    #: which tests made it significant: "learner" (held-out bin-mean fit) and / or "spectral"
    significant_by: list[str] = field(default_factory=list)
    #: held-out gain in µm along the normal on clouds not fitted on (``heldout_gain``), or None (identity candidates,
    #: which are held out inside their own groups)
    gain: dict | None = None

    @property
    def rank_score(self) -> float:
        """Score used to order effects: the learner's, or the spectral one when only the spectral test fired."""
        if self.spectral and self.spectral.get("significant") and "learner" not in self.significant_by:
            return float(self.spectral["score"])
        return float(self.score)

    def to_dict(self) -> dict:
        d = asdict(self)
        for k in ("score", "score_normal", "p_value", "p_holm", "null_mean", "null_p95"):
            d[k] = float(d[k])
        if d["gain"] is not None and not np.isfinite(d["gain"]["se_um2"]):
            d["gain"]["se_um2"] = None
        d["score_axes"] = {k: float(v) for k, v in self.score_axes.items()}
        return d


def holm(p: np.ndarray) -> np.ndarray:
    """Holm step-down adjusted p-values (family-wise error control), same order as ``p``."""
    p = np.asarray(p, dtype=float)
    m = len(p)
    if m == 0:
        return p
    order = np.argsort(p)
    adj = np.minimum(1.0, np.maximum.accumulate(p[order] * (m - np.arange(m))))
    out = np.empty(m)
    out[order] = adj
    return out


def cv_folds(groups: np.ndarray, order: np.ndarray, n_folds: int, *, by: str, block_size: int, seed: int) -> np.ndarray:
    """Fold index (N,) per point. ``by="group"``: whole groups per fold (needs ≥ 2 groups); ``by="block"``:
    interleaved blocks of ``block_size`` consecutive points (acquisition ``order``) inside each group."""
    groups = np.asarray(groups)
    if by == "group":
        ug = np.unique(groups)
        if len(ug) < 2:
            raise ValueError(f"holding out by group needs at least 2 groups (clouds or profiles), got {len(ug)}")
        k = min(n_folds, len(ug))
        rng = np.random.default_rng(seed)
        perm = rng.permutation(len(ug))
        fold_of = np.empty(len(ug), dtype=np.int64)
        fold_of[perm] = np.arange(len(ug)) % k
        return fold_of[np.searchsorted(ug, groups)]
    if by == "block":
        blk = np.asarray(order, dtype=np.int64) // max(1, block_size)
        return (blk + np.searchsorted(np.unique(groups), groups)) % n_folds
    raise ValueError(f"unknown fold scheme {by!r}")


def bin_codes(x_train: np.ndarray, x_test: np.ndarray, kind: str, n_bins: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Bin codes for training and test values: quantile bins of the training values (continuous) or one code per
    value seen in training (identity; unseen values get a dedicated empty code → predicted 0)."""
    if kind == "identity":
        vals = np.unique(x_train)
        ctr = np.searchsorted(vals, x_train)
        pos = np.clip(np.searchsorted(vals, x_test), 0, len(vals) - 1)
        cte = np.where(vals[pos] == x_test, pos, len(vals))
        return ctr, cte, len(vals) + 1
    edges = np.unique(np.quantile(x_train, np.linspace(0, 1, n_bins + 1)[1:-1]))
    return np.searchsorted(edges, x_train, side="right"), np.searchsorted(edges, x_test, side="right"), len(edges) + 1


def _fold_scores(
    R: np.ndarray, codes_tr: np.ndarray, codes_te: np.ndarray, nb: int, tr: np.ndarray, te: np.ndarray,
    shrink: float, perms: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SSE (A,) and SST (A,) on the test fold for the observed fit, and SSE (P, A) under permutations."""
    Rtr, Rte = R[tr], R[te]
    mu = Rtr.mean(axis=0)
    Rtr_c, Rte_c = Rtr - mu, Rte - mu
    cnt = np.bincount(codes_tr, minlength=nb).astype(float)
    denom = cnt + shrink
    A = R.shape[1]
    sse = np.empty(A)
    sst = (Rte_c**2).sum(axis=0)
    for a in range(A):
        m = np.bincount(codes_tr, weights=Rtr_c[:, a], minlength=nb) / denom
        sse[a] = ((Rte_c[:, a] - m[codes_te]) ** 2).sum()
    if perms is None:
        return sse, sst, np.empty((0, A))
    P = perms.shape[0]
    # Permuting residual rows against the codes == permuting the codes against the rows.
    pc = codes_tr[perms] + (np.arange(P)[:, None] * nb)  # (P, ntr)
    flat = pc.ravel()
    sse_null = np.empty((P, A))
    # Test counts per code: SSE = Σ r² − 2 Σ_b m_b S_b + Σ_b n_b m_b² with S_b, n_b the test sums/counts per code.
    nte = np.bincount(codes_te, minlength=nb).astype(float)
    for a in range(A):
        m = np.bincount(flat, weights=np.tile(Rtr_c[:, a], P), minlength=P * nb).reshape(P, nb) / denom
        ste = np.bincount(codes_te, weights=Rte_c[:, a], minlength=nb)
        sse_null[:, a] = sst[a] - 2.0 * (m * ste).sum(axis=1) + (m * m * nte).sum(axis=1)
    return sse, sst, sse_null


def score_candidate(
    R: np.ndarray, x: np.ndarray, kind: str, folds: np.ndarray, cfg: TraceConfig, rng: np.random.Generator | None,
    normal_res: np.ndarray | None = None, groups: np.ndarray | None = None,
) -> dict:
    """Held-out explained variance of ``R`` (N, A) by ``x`` and its permutation null (when ``rng`` is given).

    Continuous candidates are fitted at every resolution of ``cfg.bin_levels`` (quantile bins: 16 follow a smooth
    trend, 64-192 follow an oscillation of many periods over the candidate's range); the score is the best
    resolution's, and each permutation's null score is its own best over the same resolutions (the same permuted
    rows for every resolution), so the maximum is paid for in the p-value.

    With ``groups`` (continuous candidates, folds by group), the best resolution's fit of the residual along the
    normal (``normal_res``; else the axes summed) is also scored per held-out group: ``gain`` (``heldout_gain``)."""
    A = R.shape[1]
    levels = (0,) if kind == "identity" else tuple(cfg.bin_levels)
    L = len(levels)
    P = cfg.n_perm if rng is not None else 0
    tot_sse, tot_sst = np.zeros((L, A)), np.zeros(A)
    tot_null = np.zeros((L, P, A))
    n_sse, n_sst = np.zeros(L), 0.0
    want_gain = groups is not None and kind != "identity"
    r1 = (normal_res if normal_res is not None else R.sum(axis=1)) if want_gain else None
    glv = tuple(cfg.gain_levels)
    if want_gain:
        assert groups is not None
        _, gidx = np.unique(groups, return_inverse=True)
        gidx = gidx.reshape(-1)
        G = int(gidx.max()) + 1
        g_n = np.bincount(gidx, minlength=G).astype(float)
        g_before, g_mae_before = np.zeros(G), np.zeros(G)
        g_after, g_mae_after = np.zeros((len(glv), G)), np.zeros((len(glv), G))
        g_held = np.zeros(G, bool)
    for f in np.unique(folds):
        te = folds == f
        tr = ~te
        if tr.sum() < 2 * cfg.n_bins or te.sum() < 2:
            continue
        perms = np.argsort(rng.random((P, int(tr.sum()))), axis=1) if rng is not None else None
        for li, nbins in enumerate(levels):
            ctr, cte, nb = bin_codes(x[tr], x[te], kind, nbins)
            sse, sst, null = _fold_scores(R, ctr, cte, nb, tr, te, cfg.shrink, perms)
            tot_sse[li] += sse
            if li == 0:
                tot_sst += sst
            if rng is not None:
                tot_null[li] += null
            if normal_res is not None:
                s2, t2, _ = _fold_scores(normal_res[:, None], ctr, cte, nb, tr, te, cfg.shrink, None)
                n_sse[li] += float(s2[0])
                if li == 0:
                    n_sst += float(t2[0])
        if want_gain:
            # The correction's gain over the training groups' mean (a constant is no candidate's effect), per
            # held-out group, at every resolution of ``gain_levels`` (the best one is reported).
            assert r1 is not None
            base = r1[te] - float(r1[tr].mean())
            gte = gidx[te]
            g_before += np.bincount(gte, base**2, minlength=G)
            g_mae_before += np.bincount(gte, np.abs(base), minlength=G)
            g_held[gte] = True
            for li, nbins in enumerate(glv):
                ctr, cte, nb = bin_codes(x[tr], x[te], kind, nbins)
                rt = r1[tr] - float(r1[tr].mean())
                m = np.bincount(ctr, weights=rt, minlength=nb) / (np.bincount(ctr, minlength=nb) + cfg.shrink)
                after = base - m[cte]
                g_after[li] += np.bincount(gte, after**2, minlength=G)
                g_mae_after[li] += np.bincount(gte, np.abs(after), minlength=G)
    if tot_sst.sum() <= 0:
        raise ValueError("the residual has no variance on the held-out folds (too few points or groups to trace)")
    per_level = 1.0 - tot_sse.sum(axis=1) / tot_sst.sum()
    best = int(np.argmax(per_level))
    score = float(per_level[best])
    axes = {ax: float(1.0 - tot_sse[best, i] / tot_sst[i]) if tot_sst[i] > 0 else 0.0
            for i, ax in enumerate("xyz"[:A])}
    out = {"score": score, "score_axes": axes,
           "score_normal": float(1.0 - n_sse[best] / n_sst) if n_sst > 0 else 0.0,
           "bins": int(levels[best])}
    if want_gain:
        k = g_held & (g_n > 0)
        gb = int(np.argmin(g_after[:, k].sum(axis=1)))
        out["gain"] = {**heldout_gain(g_before[k], g_after[gb, k], g_mae_before[k], g_mae_after[gb, k], g_n[k], cfg),
                       "bins": int(glv[gb])}
    if rng is not None:
        null = (1.0 - tot_null.sum(axis=2) / tot_sst.sum()).max(axis=0)
        out.update(_p_value(score, null))
    return out


def heldout_gain(
    sse_before: np.ndarray, sse_after: np.ndarray, sae_before: np.ndarray, sae_after: np.ndarray, n: np.ndarray,
    cfg: TraceConfig,
) -> dict:
    """The gain of a correction on groups (clouds / profiles) it was not fitted on, in µm, from per-group sums (mm)
    of the squared and absolute residual along the normal before / after it, and the group sizes ``n``.

    ``mse_um2``: mean over groups of the per-group drop of the mean squared residual (µm²), ``se_um2`` its standard
    error over groups (groups are the independent units: neighbouring points, profiles and scans share errors);
    ``size_um`` = √max(mse_um2, 0): the RMS of the part of the residual the correction predicts on unseen groups —
    the effect's held-out size; ``rms_um`` / ``mae_um``: drop of the pooled RMS / MAE (µm). ``passes``: size ≥
    ``cfg.min_size_um`` and mse_um2 ≥ z × se_um2 (and > 0), z = ``cfg.gain_z`` × t₀.₉₇₅(G − 1) / 1.96."""
    n = np.maximum(n, 1.0)
    d = (sse_before - sse_after) / n * 1e6
    G = len(d)
    mse = float(d.mean()) if G else 0.0
    se = float(d.std(ddof=1) / np.sqrt(G)) if G > 1 else float("inf")
    size = float(np.sqrt(max(mse, 0.0)))
    N = float(n.sum()) if G else 1.0
    rms = float(np.sqrt(sse_before.sum() / N) - np.sqrt(max(sse_after.sum(), 0.0) / N)) * 1e3 if G else 0.0
    mae = float((sae_before.sum() - sae_after.sum()) / N) * 1e3 if G else 0.0
    # Few groups estimate the s.e. poorly: the factor grows like Student's t quantile with G − 1 degrees of freedom
    # (gain_z at many groups; × 2.2 at 3 groups, × 1.2 at 8).
    z = cfg.gain_z * (float(student_t.ppf(0.975, G - 1)) / float(norm.ppf(0.975)) if G > 1 else 1.0)
    return {"mse_um2": mse, "se_um2": se, "size_um": size, "rms_um": rms, "mae_um": mae, "n_groups": int(G),
            "z": z, "passes": bool(G > 1 and mse > 0 and size >= cfg.min_size_um and mse >= z * se)}


def _p_value(score: float, null: np.ndarray) -> dict:
    """Permutation p-value of ``score`` against ``null`` (P,), extrapolated by a normal fit beyond the resolution."""
    n_ge = int(np.sum(null >= score))
    if n_ge > 0:
        p = float((1 + n_ge) / (1 + len(null)))
    else:
        # Beyond the permutation resolution: extrapolate with a normal fit to the null (sum over many points).
        sd = max(float(null.std(ddof=1)), 1e-12)
        p = float(min(1.0 / (1 + len(null)), norm.sf((score - null.mean()) / sd)))
    return {"p_value": p, "null_mean": float(null.mean()), "null_p95": float(np.quantile(null, 0.95))}


def _poly_basis(x: np.ndarray, deg: int) -> np.ndarray:
    """Orthonormal basis (n, deg + 1) of the polynomials of degree ≤ ``deg`` in ``x`` (for detrending)."""
    z = (x - x.mean()) / max(float(x.std()), 1e-12)
    q, _ = np.linalg.qr(np.vander(z, deg + 1, increasing=True))
    return q


def spectral_test(
    R: np.ndarray, x: np.ndarray, groups: np.ndarray, folds: np.ndarray, cfg: TraceConfig,
    rng: np.random.Generator | None,
) -> dict | None:
    """Phase-free spectral test of the residual ``R`` (N, A) over the candidate ``x``, held out by group.

    Per group (cloud / profile), the residual is detrended (polynomial of degree ``cfg.spectral_detrend`` in x) and,
    at each frequency of a grid from ``spectral_min_periods`` to ``spectral_max_periods`` periods over the median
    group span of x (and below half the inverse median spacing of x), a sinusoid a·cos + b·sin with its own
    amplitude and phase is least-squares fitted per axis (the floating-mean Lomb-Scargle periodogram, written as
    batched 2×2 normal equations so that all permutations share one matrix product; scipy's ``lombscargle`` takes
    one series at a time). Power = explained fraction of the group's detrended residual variance (axes summed).
    Held out: for every group fold, the frequency of the highest power averaged over the *other* groups is read on
    the held-out groups; the score is that held-out power minus its expectation for noise (2 fitted terms per
    axis: 2 / (n − deg − 1)). Null: the residual permuted inside each group (same procedure, including the
    frequency choice). Because the phase is fitted per group, an oscillation whose phase changes from scan to scan
    is found too; ``phase_coherence`` (1: locked to x, ~0: random per group) tells whether x can predict it.

    Returns None when x gives no usable frequency range (constant, or too few distinct values).
    """
    ug, gi = np.unique(groups, return_inverse=True)
    gi = gi.reshape(-1)
    A = R.shape[1]
    spans, steps = [], []
    for k in range(len(ug)):
        xs = np.unique(x[gi == k])
        if len(xs) > 2:
            spans.append(xs[-1] - xs[0])
            steps.append(np.median(np.diff(xs)))
    if not spans or np.median(spans) <= 0:
        return None
    span = float(np.median(spans))
    fmin = cfg.spectral_min_periods / span
    fmax = min(cfg.spectral_max_periods / span, 0.5 / max(float(np.median(steps)), 1e-12))
    if fmax <= fmin:
        return None
    freqs = np.linspace(fmin, fmax, cfg.spectral_n_freq)
    P = cfg.n_perm if rng is not None else 0
    G = len(ug)
    power = np.zeros((G, len(freqs), P + 1))
    coef = np.zeros((G, len(freqs), 2, A))  # observed cos / sin coefficients per axis (mm)
    bias = np.zeros(G)
    fold_of = np.zeros(G, dtype=np.int64)
    deg = cfg.spectral_detrend
    for k in range(G):
        idx = np.flatnonzero(gi == k)
        fold_of[k] = folds[idx[0]]
        n = len(idx)
        if n < 4 * (deg + 3):
            continue
        xc = x[idx]
        Q = _poly_basis(xc, deg)
        Rc = R[idx] - Q @ (Q.T @ R[idx])
        Y = Rc
        if P and rng is not None:
            perm = np.argsort(rng.random((P, n)), axis=1)
            Yp = Rc[perm].transpose(1, 0, 2).reshape(n, P * A)
            Y = np.hstack([Rc, Yp - Q @ (Q.T @ Yp)])
        tss = (Y**2).sum(axis=0).reshape(P + 1, A).sum(axis=1)
        ph = (2.0 * np.pi) * freqs[:, None] * xc[None, :]  # absolute x: the phase is x's
        C, S = np.cos(ph), np.sin(ph)
        C -= (C @ Q) @ Q.T
        S -= (S @ Q) @ Q.T
        cc, ss, cs = (C * C).sum(1), (S * S).sum(1), (C * S).sum(1)
        det = cc * ss - cs * cs
        ok = det > 1e-9 * np.maximum(cc * ss, 1e-300)
        det = np.where(ok, det, 1.0)
        bc, bs = C @ Y, S @ Y  # (F, (P + 1) A)
        ess = (ss[:, None] * bc**2 - 2.0 * cs[:, None] * bc * bs + cc[:, None] * bs**2) / det[:, None]
        ess = np.where(ok[:, None], ess, 0.0)
        power[k] = ess.reshape(len(freqs), P + 1, A).sum(axis=2) / np.maximum(tss, 1e-300)[None, :]
        a = (ss[:, None] * bc[:, :A] - cs[:, None] * bs[:, :A]) / det[:, None]
        b = (cc[:, None] * bs[:, :A] - cs[:, None] * bc[:, :A]) / det[:, None]
        coef[k, :, 0], coef[k, :, 1] = a, b
        bias[k] = 2.0 / max(n - deg - 1, 1)
    held = np.zeros(P + 1)
    n_held = 0
    for f in np.unique(fold_of):
        te = fold_of == f
        if te.all():
            continue
        pick = power[~te].mean(axis=0).argmax(axis=0)  # (P + 1,) frequency chosen without the held-out groups
        held += (power[te][:, pick, np.arange(P + 1)] - bias[te][:, None]).sum(axis=0)
        n_held += int(te.sum())
    if n_held == 0:
        return None
    held /= n_held
    peak = int(power[:, :, 0].mean(axis=0).argmax())
    cf = coef[:, peak]  # (G, 2, A)
    amp = np.sqrt((cf**2).sum(axis=1)).max(axis=1)  # per group, amplitude of the strongest axis (mm)
    # Phase coherence along the dominant direction of the coefficients (the axes' signs may differ by group).
    flat = cf.reshape(-1, A)
    _, _, vt = np.linalg.svd(flat, full_matrices=False)
    z = cf[:, 0] @ vt[0] + 1j * (cf[:, 1] @ vt[0])
    coherence = float(np.abs(z.sum()) / max(np.abs(z).sum(), 1e-300))
    out = {"score": float(held[0]), "peak_frequency": float(freqs[peak]), "period": float(1.0 / freqs[peak]),
           "amplitude_mm": float(np.median(amp)), "phase_coherence": coherence,
           "frequency_range": [float(fmin), float(fmax)], "n_groups": int(G)}
    if P:
        out.update(_p_value(float(held[0]), held[1:]))
    return out


def spans_groups(x: np.ndarray, groups: np.ndarray) -> bool:
    """True when some value of the identity ``x`` occurs in more than one group."""
    pairs = np.unique(np.stack([np.asarray(x, dtype=float), np.asarray(groups, dtype=float)], axis=1), axis=0)
    return bool(len(pairs) > len(np.unique(pairs[:, 0])))


def trace_candidates(
    residual: np.ndarray,
    candidates: dict[str, np.ndarray],
    kinds: dict[str, str],
    groups: np.ndarray,
    order: np.ndarray,
    cfg: TraceConfig = TraceConfig(),
    *,
    normal_residual: np.ndarray | None = None,
    identity_groups: dict[str, np.ndarray] | None = None,
    meta: dict[str, dict] | None = None,
    spectral: set[str] | frozenset[str] = frozenset(),
) -> list[CandidateScore]:
    """Rank candidates by held-out explained variance of ``residual`` (N, 3) mm; significance by permutation + Holm.

    Args:
        residual: actual − predicted error per axis, mm.
        candidates: name → (N,) values (finite).
        kinds: name → "continuous" | "identity".
        groups: (N,) cloud / profile id: continuous candidates are held out by whole groups.
        order: (N,) acquisition order of each point inside its group (blocks for identity candidates).
        normal_residual: (N,) residual along the nominal normal (reported, not used for ranking).
        meta: name → {"description", "unit", "in_model"} copied into the scores.
        spectral: continuous candidates that also get the spectral test (``spectral_test``: time, positions) when
            ``cfg.spectral``; its p-values join the learner's in one Holm family.
    Returns:
        scores sorted by decreasing score (significant first).
    """
    R = np.asarray(residual, dtype=float)
    if R.ndim != 2 or R.shape[1] != 3:
        raise ValueError(f"residual must be (N, 3), got {R.shape}")
    n = len(R)
    if n < 4 * cfg.n_bins:
        raise ValueError(f"too few points to trace: {n} (need at least {4 * cfg.n_bins})")
    rng_sub = np.random.default_rng(cfg.seed)
    sel = np.sort(rng_sub.choice(n, cfg.max_points, replace=False)) if n > cfg.max_points else np.arange(n)
    R = R[sel]
    nres = None if normal_residual is None else np.asarray(normal_residual, dtype=float)[sel]
    groups = np.asarray(groups)[sel]
    order = np.asarray(order)[sel]
    folds_group = cv_folds(groups, order, cfg.n_folds, by="group", block_size=cfg.block_size, seed=cfg.seed)
    folds_block = cv_folds(groups, order, cfg.n_folds, by="block", block_size=cfg.block_size, seed=cfg.seed)
    meta = meta or {}
    scores: list[CandidateScore] = []
    for i, (name, vals) in enumerate(candidates.items()):
        x = np.asarray(vals)[sel]
        if x.shape != (len(sel),):
            raise ValueError(f"candidate {name!r} has shape {np.shape(vals)}, expected ({n},)")
        if not np.all(np.isfinite(x)):
            raise ValueError(f"candidate {name!r} has non-finite values")
        kind = kinds.get(name, "continuous")
        folds = folds_block if (kind == "identity" and not spans_groups(x, groups)) else folds_group
        rng = np.random.default_rng([cfg.seed, i])
        res: dict[str, Any]
        if np.unique(x).size < 2:
            res = {"score": 0.0, "score_axes": dict.fromkeys("xyz", 0.0), "score_normal": 0.0, "p_value": 1.0,
                   "null_mean": 0.0, "null_p95": 0.0}
        else:
            res = score_candidate(R, x, kind, folds, cfg, rng, nres, groups=groups if kind != "identity" else None)
        spec = None
        if cfg.spectral and kind != "identity" and name in spectral and np.unique(x).size > 2:
            spec = spectral_test(R, x, groups, folds_group, cfg, np.random.default_rng([cfg.seed, i, 1]))
        m = meta.get(name, {})
        scores.append(CandidateScore(
            name=name, kind=kind, score=res["score"], score_axes=res["score_axes"], score_normal=res["score_normal"],
            p_value=res["p_value"], null_mean=res["null_mean"], null_p95=res["null_p95"],
            description=m.get("description", ""), unit=m.get("unit", ""), in_model=bool(m.get("in_model", False)),
            extra={"bins": res["bins"]} if "bins" in res else {}, spectral=spec, gain=res.get("gain"),
        ))
    # One Holm family over every test made (learner tests of all candidates + spectral tests).
    pv = [s.p_value for s in scores] + [s.spectral["p_value"] for s in scores if s.spectral]
    adj = holm(np.array(pv))
    k = len(scores)
    for s, pa in zip(scores, adj[:k], strict=True):
        s.p_holm = float(pa)
        # Continuous candidates: by their held-out gain in µm on unseen groups (size and uncertainty); identity
        # candidates (scored inside their own groups; diagnostic): by the share of the residual they explain.
        # With very few held-out groups the s.e. is poorly known: a continuous candidate explaining ≥ min_effect of
        # the residual with a held-out size ≥ min_size_um also counts (the size check is the same).
        big = ((s.gain["passes"] or (s.score >= cfg.min_effect and s.gain["size_um"] >= cfg.min_size_um))
               if s.gain is not None else s.score >= cfg.min_effect)
        s.significant_by = ["learner"] if (pa <= cfg.alpha and big) else []
    for s, pa in zip([s for s in scores if s.spectral], adj[k:], strict=True):
        assert s.spectral is not None
        s.spectral["p_holm"] = float(pa)
        s.spectral["significant"] = bool(pa <= cfg.alpha and s.spectral["score"] >= cfg.min_effect)
        if s.spectral["significant"]:
            s.significant_by.append("spectral")
    for s in scores:
        s.significant = bool(s.significant_by)
    scores.sort(key=lambda s: (not s.significant, -s.rank_score))
    return scores
