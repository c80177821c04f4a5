"""A periodic effect of scan time: one sinusoid of the time since scan start, the same in every scan (phase-locked),
fitted on some clouds and judged on the clouds it was not fitted on.

Model, along the nominal normal (mm): ``r ≈ c + a·cos(2πft) + b·sin(2πft)``. Fitted on the training clouds with one
intercept per cloud (a per-cloud offset is no part of the vibration and must not steer it; the sinusoid is fitted on
the within-cloud variation of residual and basis), the frequency chosen on those clouds only (the largest explained
sum of squares over a grid from half a period over the longest scan to 64 periods over the median scan, below half
the sampling rate). Applied to an unseen cloud it predicts ``c`` (the training clouds' mean) plus the sinusoid at that
cloud's own times: a vibration locked to the scan start transfers; per-profile offsets, fitted inside a recording,
do not (``transfer_compare``).

Everything vectorised over points and frequencies (frequencies in chunks to bound the memory).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .trace import TraceConfig, heldout_gain

__all__ = ["PERIODIC_NAMES", "PeriodicFit", "fit_periodic", "frequency_grid", "periodic_gain", "transfer_compare"]

#: Candidates of scan time (s since the scan start) that get the periodic transfer test.
PERIODIC_NAMES = frozenset({"field_t", "field_time"})
MAX_FREQ = 512
CHUNK = 64
MAX_PERIODS = 16.0  # highest frequency: this many periods over the median scan span
RIDGE = 0.02  # ridge on the sinusoid's coefficients, relative to the raw basis energy
REFINE_PEAKS, REFINE_POINTS = 3, 9


@dataclass(frozen=True)
class PeriodicFit:
    """``c + a·cos(2πft) + b·sin(2πft)`` (mm; f in 1 / unit of t)."""

    freq: float
    a: float
    b: float
    c: float

    @property
    def amplitude(self) -> float:
        return float(np.hypot(self.a, self.b))

    @property
    def phase(self) -> float:
        """Phase (rad) of ``amplitude·sin(2πft + phase)``."""
        return float(np.arctan2(self.a, self.b))

    def predict(self, t: np.ndarray) -> np.ndarray:
        ph = 2.0 * np.pi * self.freq * np.asarray(t, dtype=float)
        return self.c + self.a * np.cos(ph) + self.b * np.sin(ph)

    def to_dict(self, unit: str = "s") -> dict:
        return {"frequency": self.freq, "frequency_unit": f"1/{unit}", "period": 1.0 / self.freq,
                "amplitude_um": 1e3 * self.amplitude, "phase_rad": self.phase}


def frequency_grid(t: np.ndarray, groups: np.ndarray, max_periods: float = MAX_PERIODS) -> np.ndarray:
    """Frequencies (1 / unit of t) from half a period over T = max(longest group span, largest |t|) to
    ``max_periods`` over the median span (and below half the inverse median spacing), stepped by 1 / (2 T)
    (≤ ``MAX_FREQ``; ``fit_periodic`` refines around the best peaks)."""
    _, gi = np.unique(groups, return_inverse=True)
    gi = gi.reshape(-1)
    spans, steps = [], []
    for k in range(int(gi.max()) + 1):
        ts = np.unique(t[gi == k])
        if len(ts) > 2:
            spans.append(ts[-1] - ts[0])
            steps.append(np.median(np.diff(ts)))
    if not spans or max(spans) <= 0:
        return np.empty(0)
    # The phase is locked to t = 0 (the scan start), so the resolution needed is set by the largest |t|, not by the
    # span of one scan: a scan seen late in its recording pins the frequency finely.
    tmax = max(float(max(spans)), float(np.max(np.abs(t))))
    fmin = 0.5 / tmax
    fmax = min(max_periods / max(float(np.median(spans)), 1e-12), 0.5 / max(float(np.median(steps)), 1e-12))
    if fmax <= fmin:
        return np.empty(0)
    n = int(min(MAX_FREQ, max(8, np.ceil((fmax - fmin) * 2.0 * tmax))))
    return np.linspace(fmin, fmax, n)


def fit_periodic(r: np.ndarray, t: np.ndarray, groups: np.ndarray, freqs: np.ndarray) -> PeriodicFit | None:
    """Least-squares sinusoid of ``t`` with one intercept per group, at the grid frequency that explains most of the
    within-group variation of ``r`` (mm). None when no frequency is usable."""
    if len(freqs) == 0 or len(r) < 8:
        return None
    _, gi = np.unique(groups, return_inverse=True)
    gi = gi.reshape(-1)
    cnt = np.bincount(gi).astype(float)

    def demean(v: np.ndarray) -> np.ndarray:  # (F, n) or (n,): minus the per-group mean
        if v.ndim == 1:
            return v - (np.bincount(gi, v) / cnt)[gi]
        out = np.empty_like(v)
        for i in range(v.shape[0]):
            out[i] = v[i] - (np.bincount(gi, v[i]) / cnt)[gi]
        return out

    rd = demean(np.asarray(r, dtype=float))
    lam = RIDGE * len(r) / 2.0  # ridge on (a, b): a fraction of the raw basis energy (n / 2 per term)

    def scan(f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ess, aa, bb = np.empty(len(f)), np.empty(len(f)), np.empty(len(f))
        for s0 in range(0, len(f), CHUNK):
            fc = f[s0:s0 + CHUNK]
            ph = (2.0 * np.pi) * fc[:, None] * t[None, :]
            C, S = demean(np.cos(ph)), demean(np.sin(ph))
            cc, ss, cs = (C * C).sum(1) + lam, (S * S).sum(1) + lam, (C * S).sum(1)
            bc, bs = C @ rd, S @ rd
            det = cc * ss - cs * cs
            a = (ss * bc - cs * bs) / det
            b = (cc * bs - cs * bc) / det
            ess[s0:s0 + CHUNK] = a * bc + b * bs
            aa[s0:s0 + CHUNK], bb[s0:s0 + CHUNK] = a, b
        return ess, aa, bb

    # Coarse grid, then a finer one around the best few coarse peaks.
    ess, aa, bb = scan(freqs)
    step = float(freqs[1] - freqs[0]) if len(freqs) > 1 else float(freqs[0])
    top = np.argsort(-ess)[:REFINE_PEAKS]
    fine = np.unique(np.concatenate([freqs[k] + step * np.linspace(-0.5, 0.5, REFINE_POINTS) for k in top]))
    fine = fine[fine > 0]
    e2, a2, b2 = scan(fine)
    allf, alle = np.concatenate([freqs, fine]), np.concatenate([ess, e2])
    alla, allb = np.concatenate([aa, a2]), np.concatenate([bb, b2])
    k = int(np.argmax(alle))
    best = (float(alle[k]), float(allf[k]), float(alla[k]), float(allb[k]))
    if best[0] <= 0:
        return None
    _, fq, a_, b_ = best
    ph = 2.0 * np.pi * fq * t
    c = float(np.mean(r - a_ * np.cos(ph) - b_ * np.sin(ph)))
    return PeriodicFit(fq, a_, b_, c)


def _group_sums(gidx: np.ndarray, G: int, before: np.ndarray,
                after: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return (np.bincount(gidx, before**2, minlength=G), np.bincount(gidx, after**2, minlength=G),
            np.bincount(gidx, np.abs(before), minlength=G), np.bincount(gidx, np.abs(after), minlength=G))


def periodic_gain(r: np.ndarray, t: np.ndarray, groups: np.ndarray, folds: np.ndarray, cfg: TraceConfig,
                  unit: str = "s") -> dict | None:
    """Held-out gain (``trace.heldout_gain``, µm) of the phase-locked sinusoid of ``t`` on the residual along the
    normal ``r`` (mm): for each fold of whole groups, fitted (frequency included) on the other groups, applied to
    the held-out ones, against the other groups' mean. Also the fit on all groups (frequency, amplitude, phase) and
    the frequencies chosen per fold. None when ``t`` gives no frequency range."""
    freqs = frequency_grid(t, groups)
    if len(freqs) == 0:
        return None
    _, gidx = np.unique(groups, return_inverse=True)
    gidx = gidx.reshape(-1)
    G = int(gidx.max()) + 1
    sums = [np.zeros(G) for _ in range(4)]
    held = np.zeros(G, bool)
    chosen = []
    for f in np.unique(folds):
        te = folds == f
        tr = ~te
        if len(np.unique(gidx[tr])) < 2 or not te.any():
            continue
        fit = fit_periodic(r[tr], t[tr], gidx[tr], freqs)
        base = r[te] - float(r[tr].mean())
        after = base if fit is None else r[te] - fit.predict(t[te])
        chosen.append(None if fit is None else fit.freq)
        for acc, v in zip(sums, _group_sums(gidx[te], G, base, after), strict=True):
            acc += v
        held[gidx[te]] = True
    if not held.any():
        return None
    n = np.bincount(gidx, minlength=G).astype(float)
    gain = heldout_gain(sums[0][held], sums[1][held], sums[2][held], sums[3][held], n[held], cfg)
    full = fit_periodic(r, t, gidx, freqs)
    return {**gain, "fit": None if full is None else full.to_dict(unit), "fold_frequencies": chosen,
            "frequency_range": [float(freqs[0]), float(freqs[-1])]}


def transfer_compare(r: np.ndarray, t: np.ndarray, line: np.ndarray, groups: np.ndarray, folds: np.ndarray,
                     cfg: TraceConfig, periodic: dict | None = None) -> dict:
    """Which one predicts scans it was not fitted on: a phase-locked sinusoid of scan time ``t``, or per-profile
    offsets? Both are fitted on the other groups of each fold of whole groups (clouds) and judged on the held-out
    ones (``heldout_gain``, µm, residual along the normal ``r``, mm). The per-profile offsets of a new scan are not
    known; the best they can carry over is the offset of the same profile index (``line``) averaged over the
    training scans (shrunken like the trace's bin means). ``periodic``: ``periodic_gain``'s result, when already
    computed. Also the within-recording gain of the profile offsets (cross-fitted inside each cloud, the way they
    "explain" the residual of the scans they were fitted on), to show the mimicry."""
    per = periodic if periodic is not None else periodic_gain(r, t, groups, folds, cfg)
    _, gidx = np.unique(groups, return_inverse=True)
    gidx = gidx.reshape(-1)
    G = int(gidx.max()) + 1
    li = np.asarray(line, dtype=np.int64)
    nl = int(li.max()) + 1 if len(li) else 1
    sums = [np.zeros(G) for _ in range(4)]
    held = np.zeros(G, bool)
    for f in np.unique(folds):
        te = folds == f
        tr = ~te
        if not tr.any() or not te.any():
            continue
        mu = float(r[tr].mean())
        m = np.bincount(li[tr], r[tr] - mu, minlength=nl) / (np.bincount(li[tr], minlength=nl) + cfg.shrink)
        base = r[te] - mu
        for acc, v in zip(sums, _group_sums(gidx[te], G, base, base - m[li[te]]), strict=True):
            acc += v
        held[gidx[te]] = True
    n = np.bincount(gidx, minlength=G).astype(float)
    prof = (heldout_gain(sums[0][held], sums[1][held], sums[2][held], sums[3][held], n[held], cfg)
            if held.any() else None)
    # Within the recording: each profile's own offset (cloud, line), cross-fitted on alternate points of that profile
    # (its points share one t).
    key = gidx.astype(np.int64) * nl + li
    _, ki = np.unique(key, return_inverse=True)
    ki = ki.reshape(-1)
    half = np.arange(len(r)) % 2 == 0
    K = int(ki.max()) + 1
    within_after = r.copy()
    for fit_rows in (half, ~half):
        m = np.bincount(ki[fit_rows], r[fit_rows], minlength=K) / (np.bincount(ki[fit_rows], minlength=K) + 1.0)
        within_after[~fit_rows] = r[~fit_rows] - m[ki[~fit_rows]]
    w0, w1, w2, w3 = _group_sums(gidx, G, r, within_after)
    within = heldout_gain(w0, w1, w2, w3, n, cfg)
    per_ok = bool(per and per["passes"])
    prof_ok = bool(prof and prof["passes"])
    if per_ok and (not prof_ok or per["mse_um2"] > prof["mse_um2"]):  # type: ignore[index]
        transfers = "periodic"
    elif prof_ok:
        transfers = "profile_index"
    else:
        transfers = "neither"
    return {"periodic": per, "profile_offsets_by_index": prof, "profile_offsets_within_recording": within,
            "transfers": transfers}
