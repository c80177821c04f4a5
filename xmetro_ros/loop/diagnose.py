"""Diagnostic findings of the loop: effects that need the ground truth of the scan they correct.

A per-profile, per-pose, per-pass or per-scan offset is fitted on the evaluated points' own ground truth (cross-fit
inside each identity): a live node, which sees a new scan without its ground truth, cannot apply it. Such findings
are reported with their size, their structure and what would fix them, never as a live improvement
(docs/closed-loop.md, "Two kinds of findings"). Lengths mm in the data, µm in the summaries.

Per-identity offsets (``offset_table``): the rigid translation w of each identity (``correct.fit_offsets``: n·w ≈
residual·n) fitted on all its points, and its uncertainty from a bootstrap over blocks of consecutive points
inside each identity (blocks, not points: neighbouring residuals are correlated). The direction least constrained
by the identity's normals (e.g. along a single profile's plane normal) is reported by its conditioning.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .correct import fit_offsets

__all__ = ["FIXES", "fix_for", "offset_table", "oscillation_finding"]

#: What would remove a diagnostic effect, by the kind of identity.
FIXES = {
    "pose": ("the pose chain places each profile wrongly (robot flange pose × hand-eye): re-calibrate the hand-eye "
             "transform and the robot's poses (or track the head with a laser tracker); no feature of a scan's own "
             "points can predict a per-pose offset"),
    "profile": ("per-profile offsets inside a scan: profile trigger / encoder jitter or vibration of the motion "
                "axis; fix the axis or the profile timing (or record the axis position as a field the model can use)"),
    "pass": ("per-pass offsets: the passes of a scan are not registered to each other (motion-axis repeatability, "
             "pass-to-pass alignment); register the passes (reference features, encoder) before judging the scan"),
    "cloud": ("per-scan offsets: the artifact's placement or the position given for each scan (fixture, fitted "
              "centre) differs from scan to scan; check the fixture / give known positions"),
    "field": "offsets per value of an identity field: find what the field identifies and register it",
    "pattern": ("the error repeats at a sensor position as a shape along the laser line (speckle, the surface's "
                "texture, a per-pose error that is no rigid offset): only repeats of that position can correct it "
                "(a per-pose correction map, where a cell revisits fixed poses); at a new position no feature of the "
                "profile predicts it, and U has to cover it"),
    "oscillation": ("an oscillation whose phase is not locked to the variable (it changes from scan to scan): a "
                    "vibration of the head or the axis; isolate it, or record its phase (e.g. an accelerometer "
                    "field) so that a feature can follow it"),
    "periodic": ("a periodic structure, partly locked to the variable, that a feature learnt on the training "
                 "groups did not carry to held-out ones: too few groups to learn it, or a structure that changes "
                 "from group to group; calibrate it directly (e.g. a distortion map along the variable) with more "
                 "scans"),
}
#: phase coherence from which an oscillation counts as locked to its variable (``run.LoopConfig``'s default)
LOCKED_COHERENCE = 0.5


def fix_for(name: str, hold_by: str) -> tuple[str, str]:
    """(structure, fix) for an identity candidate's offsets."""
    if name == "profile_identity":
        if hold_by == "profile":
            return "per-profile (per-pose) rigid offset", FIXES["pose"]
        return "per-profile rigid offset inside each scan", FIXES["profile"]
    if name == "cloud_identity":
        return "per-scan rigid offset", FIXES["cloud"]
    if name == "pose_line_pattern":
        return "per-position pattern along the laser line (0.5 mm cells)", FIXES["pattern"]
    low = name.lower()
    if "pass" in low:
        return "per-pass rigid offset", FIXES["pass"]
    if "pose" in low:
        return "per-pose rigid offset", FIXES["pose"]
    if "profile" in low:
        return "per-profile rigid offset", FIXES["profile"]
    return "per-identity rigid offset", FIXES["field"]


def _identity_names(keys: np.ndarray, group: np.ndarray, group_names: list[str], raw: np.ndarray | None,
                    field: str) -> dict[float, str]:
    uk, first = np.unique(keys, return_index=True)
    out = {}
    for k, i in zip(uk, first, strict=True):
        g = int(group[i])
        gname = group_names[g] if g < len(group_names) else f"group{g}"
        out[float(k)] = gname if raw is None else f"{gname} {field}={raw[i]:g}"
    return out


def offset_table(
    residual: np.ndarray, normals: np.ndarray, keys: np.ndarray, order: np.ndarray, group: np.ndarray,
    group_names: list[str], *, raw: np.ndarray | None = None, field: str = "", block_size: int = 24,
    ridge: float = 1e-3, n_boot: int = 200, seed: int = 0, max_rows: int = 100,
) -> dict[str, Any]:
    """Per-identity offsets (mm) with bootstrap standard errors, and a summary in µm.

    Args:
        residual: (N, 3) mm, what the live model leaves (actual − predicted), all roles.
        keys: (N,) identity code of each point (``candidates.build_candidates``).
        order: acquisition order inside the group (the bootstrap resamples blocks of ``block_size``).
        raw: the identity field's own values (for naming), None for group identities.
        max_rows: at most this many identities listed (the summary covers all).
    """
    keys = np.asarray(keys, dtype=float)
    uk, w = fit_offsets(residual, normals, keys, ridge)
    # Bootstrap over blocks: a block = (identity, order // block_size). np.unique sorts the blocks by identity, so
    # each identity's blocks are contiguous; a draw replaces every block by a random block of the same identity.
    blk = np.unique(np.stack([keys, np.asarray(order, dtype=np.int64) // max(1, block_size)], axis=1), axis=0,
                    return_inverse=True)[1].reshape(-1)
    nblk = int(blk.max()) + 1
    blk_key = np.zeros(nblk)
    blk_key[blk] = keys
    kidx = np.searchsorted(uk, blk_key)
    sizes = np.bincount(kidx, minlength=len(uk))
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    rng = np.random.default_rng(seed)
    boots = np.full((n_boot, len(uk), 3), np.nan)
    idx = np.arange(len(keys))
    for b in range(n_boot):
        pick = starts[kidx] + (rng.random(nblk) * sizes[kidx]).astype(np.int64)
        rep = np.repeat(idx, np.bincount(pick, minlength=nblk)[blk])
        ukb, wb = fit_offsets(residual[rep], normals[rep], keys[rep], ridge)
        boots[b, np.searchsorted(uk, ukb)] = wb
    se = np.nanstd(boots, axis=0, ddof=1)
    # Conditioning of each identity's normal equations: how well its normals fix each direction.
    n = np.asarray(normals, dtype=float)
    inv = np.searchsorted(uk, keys)
    M = np.zeros((len(uk), 3, 3))
    for i in range(3):
        for j in range(3):
            M[:, i, j] = np.bincount(inv, weights=n[:, i] * n[:, j], minlength=len(uk))
    ev = np.linalg.eigvalsh(M / np.maximum(np.bincount(inv, minlength=len(uk)), 1)[:, None, None])
    names = _identity_names(keys, group, group_names, raw, field)
    mag = np.linalg.norm(w, axis=1) * 1e3
    rows = [{"identity": names[float(k)], "offset_um": [round(float(v) * 1e3, 2) for v in w[i]],
             "se_um": [round(float(v) * 1e3, 2) for v in se[i]], "norm_um": round(float(mag[i]), 2),
             "weakest_direction_eig": round(float(ev[i, 0]), 4)} for i, k in enumerate(uk)]
    mean_w = w.mean(axis=0)
    return {
        "n_identities": len(uk), "per_identity_shown": min(len(rows), max_rows),
        "median_um": float(np.median(mag)), "max_um": float(mag.max()),
        "median_se_um": float(np.nanmedian(np.linalg.norm(se, axis=1)) * 1e3),
        "mean_offset_um": [float(v) * 1e3 for v in mean_w],
        # 1: every identity shifted the same way (a systematic translation); ~0: scattered
        "direction_coherence": float(np.linalg.norm(mean_w) / max(np.linalg.norm(w, axis=1).mean(), 1e-300)),
        "bootstrap": {"n": n_boot, "unit": f"blocks of {block_size} consecutive points"},
        "per_identity": rows[:max_rows],
    }


def oscillation_finding(score: dict, name: str, unit: str, trace_gain: float | None) -> dict[str, Any]:
    """A significant oscillation that the variable as a feature could not predict (phase not locked)."""
    sp = score.get("spectral") or {}
    return {
        "variable": name, "kind": "oscillation", "structure": f"oscillation over {name}",
        "peak_frequency": sp.get("peak_frequency"), "period": sp.get("period"),
        "unit": f"cycles per {unit}" if unit else "cycles per unit", "amplitude_um": 1e3 * sp.get("amplitude_mm", 0.0),
        "phase_coherence": sp.get("phase_coherence"), "spectral_score": sp.get("score"),
        "p_holm": sp.get("p_holm"), "trace_gain_as_feature": trace_gain,
        "needs_ground_truth": True,
        "fix": FIXES["periodic" if (sp.get("phase_coherence") or 0.0) >= LOCKED_COHERENCE else "oscillation"],
    }
