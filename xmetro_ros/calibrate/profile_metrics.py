"""Scores of a profile model on real profiles (pure numpy on a ``ProfileTable`` and the model's d and U; mm in,
µm out where the name says so). Every score compares the product with what the data say, never with itself:

- segmentation: per profile, IoU of the points the product keeps as the sphere with the file's label-1 points;
- systematic error: MAE of d against the repeat-mean deviation (``systematic``, positions with ≥ ``min_repeats``
  repeats) next to the best constant (the median of the targets themselves: no constant does better in MAE)
  and a per-incidence-bin mean fitted on training rows; R² of d against the same targets;
- uncertainty: coverage of |measured − d| ≤ U per axis of the laser plane (x, z: d × n, U × |n|) overall and per
  10° bin of |in-plane incidence|; U next to the repeat spread (the random part) and the repeat mean;
- quality: ROC-AUC of a per-point score (U) for "labelled 0 but on the sphere" against label-1 points.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .profile_table import ProfileTable

__all__ = ["bin_mean_baseline", "coverage_table", "quality_auc", "segmentation_iou", "systematic_scores"]

UM = 1000.0


def segmentation_iou(table: ProfileTable, profiles: np.ndarray) -> np.ndarray:
    """(len(profiles),) IoU of kept points vs label-1 points per profile (NaN for a profile without labels)."""
    if table.label1_count is None:
        return np.full(len(profiles), np.nan)
    out = np.full(len(profiles), np.nan)
    inter = np.bincount(table.profile, weights=(table.kept & (table.label == 1)).astype(float),
                        minlength=len(table.names))
    kept = np.bincount(table.profile, weights=table.kept.astype(float), minlength=len(table.names))
    for i, k in enumerate(np.asarray(profiles, dtype=np.int64)):
        n1 = table.label1_count[k]
        if n1 >= 0:
            union = kept[k] + n1 - inter[k]
            out[i] = inter[k] / union if union > 0 else 0.0
    return out


def bin_mean_baseline(angle_deg: np.ndarray, deviation: np.ndarray, at_angle: np.ndarray,
                      bin_deg: float = 5.0) -> np.ndarray:
    """The honest baseline: the mean training deviation per ``bin_deg`` bin of signed in-plane incidence,
    evaluated at ``at_angle`` (the overall mean in a bin training never reached)."""
    b = np.floor(np.asarray(angle_deg) / bin_deg).astype(np.int64)
    off = int(b.min()) if len(b) else 0
    sums = np.bincount(b - off, weights=deviation)
    cnt = np.bincount(b - off)
    mean_all = float(np.mean(deviation)) if len(deviation) else 0.0
    bq = np.floor(np.asarray(at_angle) / bin_deg).astype(np.int64) - off
    inside = (bq >= 0) & (bq < len(cnt))
    out = np.full(len(bq), mean_all)
    ok = inside.copy()
    ok[inside] = cnt[bq[inside]] > 0
    out[ok] = sums[bq[ok]] / cnt[bq[ok]]
    return out


def systematic_scores(target: np.ndarray, d: np.ndarray, baseline: np.ndarray) -> dict[str, float]:
    """MAE (µm) of d, of the best constant and of ``baseline`` against ``target`` (mm), their ratios, R² of d."""
    t = np.asarray(target, dtype=np.float64)
    const = float(np.median(t))
    mae_d = float(np.mean(np.abs(t - d))) * UM
    mae_c = float(np.mean(np.abs(t - const))) * UM
    mae_b = float(np.mean(np.abs(t - baseline))) * UM
    r2 = float(1.0 - np.sum((t - d) ** 2) / np.sum((t - t.mean()) ** 2))
    r2_b = float(1.0 - np.sum((t - baseline) ** 2) / np.sum((t - t.mean()) ** 2))
    return {"points": len(t), "mae_d_um": mae_d, "mae_best_constant_um": mae_c, "best_constant_um": const * UM,
            "mae_bin_baseline_um": mae_b, "d_vs_constant": mae_d / mae_c, "d_vs_bin_baseline": mae_d / mae_b,
            "r2_d": r2, "r2_bin_baseline": r2_b, "target_std_um": float(np.std(t)) * UM}


def coverage_table(deviation: np.ndarray, d: np.ndarray, U: np.ndarray, normals: np.ndarray, angle_deg: np.ndarray,
                   spread: np.ndarray | None = None, bin_deg: float = 10.0) -> dict[str, Any]:
    """Coverage of the per-axis intervals (x, z) overall and per |incidence| bin, U and the repeat spread (µm).
    Points with NaN U count as not covered (a published point must carry a U that holds)."""
    n = np.asarray(normals, dtype=np.float64)
    e = np.asarray(deviation)[:, None] * n
    dd = np.asarray(d)[:, None] * n
    uu = np.asarray(U)[:, None] * np.abs(n)
    cov = np.abs(e - dd) <= np.where(np.isfinite(uu), uu, -1.0)
    b = np.clip(np.floor(np.abs(angle_deg) / bin_deg), 0, int(90 / bin_deg) - 1).astype(np.int64)
    rows: list[dict[str, Any]] = []
    for k in range(int(90 / bin_deg)):
        s = b == k
        if not s.any():
            continue
        row = {"bin_deg": [k * bin_deg, (k + 1) * bin_deg], "points": int(s.sum()),
               "coverage_x": float(cov[s, 0].mean()), "coverage_z": float(cov[s, 1].mean()),
               "coverage_normal": float(np.mean(np.abs(np.asarray(deviation)[s] - np.asarray(d)[s])
                                                <= np.nan_to_num(np.asarray(U)[s], nan=-1.0))),
               "U_median_um": float(np.nanmedian(np.asarray(U)[s])) * UM,
               "abs_error_p95_um": float(np.quantile(np.abs(np.asarray(deviation)[s] - np.asarray(d)[s]), 0.95)) * UM}
        if spread is not None:
            sp = np.asarray(spread)[s]
            sp = sp[np.isfinite(sp)]
            row["repeat_spread_rms_um"] = float(np.sqrt(np.mean(sp ** 2))) * UM if len(sp) else None
        rows.append(row)
    return {"points": len(b), "coverage_x": float(cov[:, 0].mean()), "coverage_z": float(cov[:, 1].mean()),
            "min_bin_coverage": float(min(min(r["coverage_x"], r["coverage_z"]) for r in rows)) if rows else None,
            "U_median_um": float(np.nanmedian(U)) * UM, "bins": rows}


def quality_auc(score: np.ndarray, positive: np.ndarray, negative: np.ndarray) -> float:
    """ROC-AUC of ``score`` separating ``positive`` rows (expected high) from ``negative`` rows (ties count ½)."""
    from scipy.stats import rankdata

    s = np.concatenate([np.asarray(score)[positive], np.asarray(score)[negative]])
    n_pos, n_neg = int(np.sum(positive)), int(np.sum(negative))
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    r = rankdata(s)
    return float((r[:n_pos].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))
