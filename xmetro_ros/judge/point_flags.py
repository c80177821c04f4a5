"""Compiled (numba, parallel) per-point flags and decisions of a judged scan, and their scatter into the cloud's grid.

One pass over the kept points gives what ``ScanHandler.process`` built from a dozen numpy expressions (each a full
pass with its temporaries): the GRAZING_INCIDENCE / GRAZING_VIEW bits (:func:`flags.angle_flags`), the per-feature
OUT_OF_DOMAIN range check (:func:`flags.domain_flags`) and the multivariate and shape ones, each with its reason bit
(DOMAIN_FEATURES, DOMAIN_MULTIVARIATE, DOMAIN_SHAPE), UNRELIABLE_NORMAL,
OVER_TOLERANCE on |d|, INVALID_POINT for a non-finite prediction, NO_UNCERTAINTY, and the ISO 14253-1 decision
class (:func:`flags.point_decisions`) with its NON_CONFORMING / UNDECIDED bits. A second pass writes d, U, the flags
and the classes into the (N,) cloud order and gives every point with a non-finite d and no flag INVALID_POINT.

Same results as the numpy expressions (test/test_point_flags.py): each comparison is made in the type numpy makes it
in (float32 features against float32 bounds, float32 N·L widened to float64 against the float64 cosine, normal
quality in float32); |d| and |U| are sqrt of the sum of squares in row order, which einsum may sum in another order
(the last bit of |d| can differ, so a point exactly at the tolerance could be classed differently: not seen in the
tests). Rows are independent, so the bits do not depend on the thread count.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit, prange

from ..compute import threads as _threads  # noqa: F401 - the threading layer, before any parallel kernel runs
from . import flags as fl

__all__ = ["NO_DECISION", "base_flags", "kept_point_flags", "point_masks", "scatter_kept"]

NO_DECISION = 255  # decision class of a point without a finite prediction

_PAR: dict[str, Any] = {"cache": True, "nogil": True, "error_model": "numpy", "parallel": True}
_GI, _GV = np.uint16(fl.FLAG_GRAZING_INCIDENCE), np.uint16(fl.FLAG_GRAZING_VIEW)
_UNREL = np.uint16(fl.FLAG_UNRELIABLE_NORMAL)
_OVER, _INVALID = np.uint16(fl.FLAG_OVER_TOLERANCE), np.uint16(fl.FLAG_INVALID_POINT)
_NOU, _NONCONF = np.uint16(fl.FLAG_NO_UNCERTAINTY), np.uint16(fl.FLAG_NON_CONFORMING)
_UNDEC = np.uint16(fl.FLAG_UNDECIDED)
_CONF_C, _NONCONF_C, _UNDEC_C = np.uint8(fl.CONFORMING), np.uint8(fl.NON_CONFORMING), np.uint8(fl.UNDECIDED)
_NODEC = np.uint8(NO_DECISION)
_OOV, _OUTLIER = np.uint16(fl.FLAG_OUT_OF_VOLUME), np.uint16(fl.FLAG_OUTLIER)
# OUT_OF_DOMAIN with its reason
_OOD_F = np.uint16(fl.FLAG_OUT_OF_DOMAIN | fl.FLAG_DOMAIN_FEATURES)
_OOD_MV = np.uint16(fl.FLAG_OUT_OF_DOMAIN | fl.FLAG_DOMAIN_MULTIVARIATE)
_OOD_S = np.uint16(fl.FLAG_OUT_OF_DOMAIN | fl.FLAG_DOMAIN_SHAPE)


@njit(**_PAR)
def _point_masks(p, half_width, finite, outside):  # pragma: no cover - compiled
    n_valid = 0
    for i in prange(p.shape[0]):
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        f = np.isfinite(x) and np.isfinite(y) and np.isfinite(z)
        # NaN compares False: a point with a NaN coordinate is outside only by a finite one beyond the volume
        o = abs(x) > half_width or abs(y) > half_width or abs(z) > half_width
        finite[i] = f
        outside[i] = o
        if f and not o:
            n_valid += 1
    return n_valid


def point_masks(points: np.ndarray, half_width_mm: float) -> tuple[np.ndarray, np.ndarray, int]:
    """(finite (N,), outside (N,), valid count) of a scan's points (any shape ending in 3, mm), in one pass split
    over the judge's threads: finite x, y and z (``Scan.valid_mask``); a coordinate beyond ±``half_width_mm`` (the
    working volume; ±inf counts, NaN does not); finite and inside."""
    p = np.asarray(points).reshape(-1, 3)
    finite = np.empty(len(p), np.bool_)
    outside = np.empty(len(p), np.bool_)
    n = _point_masks(p, np.float64(half_width_mm), finite, outside)
    return finite, outside, int(n)


@njit(**_PAR)
def _base_flags(finite, outside, outlier, flags):  # pragma: no cover - compiled
    for i in prange(flags.shape[0]):
        f = np.uint16(0)
        if not finite[i]:
            f |= _INVALID
        if outside[i]:
            f |= _OOV
        flags[i] = f
    for r in prange(outlier.shape[0]):  # distinct indices
        flags[outlier[r]] |= _OUTLIER


def base_flags(finite: np.ndarray, outside: np.ndarray, outlier: np.ndarray) -> np.ndarray:
    """(N,) uint16 flags before the kept points' own: INVALID_POINT where ``finite`` is False, OUT_OF_VOLUME where
    ``outside``, OUTLIER at the distinct flat indices ``outlier``."""
    idx = np.ascontiguousarray(outlier, dtype=np.int64)
    if len(idx) and (idx.min() < 0 or idx.max() >= len(finite)):
        raise ValueError(f"outlier index outside the cloud's {len(finite)} points")
    flags = np.empty(len(finite), np.uint16)
    _base_flags(np.ascontiguousarray(finite, np.bool_), np.ascontiguousarray(outside, np.bool_), idx, flags)
    return flags


@njit(**_PAR)
def _kept(pred, U, cos_i, cos_v, thr_i, thr_v, X, lo_m, hi_m, mv_ood, shape_ood, nq, nq_min, tol, simple,
          flags, cls):  # pragma: no cover - compiled
    m = pred.shape[0]
    f_n = X.shape[1]
    use_mv = mv_ood.shape[0] == m
    use_shape = shape_ood.shape[0] == m
    negative = 0
    for i in prange(m):
        f = np.uint16(0)
        if np.float64(cos_i[i]) < thr_i:
            f |= _GI
        if np.float64(cos_v[i]) < thr_v:
            f |= _GV
        for j in range(f_n):
            x = X[i, j]
            if x < lo_m[j] or x > hi_m[j]:
                f |= _OOD_F
                break
        if use_mv and mv_ood[i]:
            f |= _OOD_MV
        if use_shape and shape_ood[i]:
            f |= _OOD_S
        if nq[i] < nq_min:
            f |= _UNREL
        p0, p1, p2 = pred[i, 0], pred[i, 1], pred[i, 2]
        dn = np.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
        if dn > tol:
            f |= _OVER
        c = _NODEC
        if np.isfinite(p0) and np.isfinite(p1) and np.isfinite(p2):
            u0, u1, u2 = U[i, 0], U[i, 1], U[i, 2]
            if not (np.isfinite(u0) and np.isfinite(u1) and np.isfinite(u2)):
                f |= _NOU
            if u0 < 0.0 or u1 < 0.0 or u2 < 0.0:
                negative += 1
            if simple:
                c = _CONF_C if dn <= tol else _NONCONF_C
            else:
                un = np.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
                c = _UNDEC_C  # NaN U compares False: undecided
                if dn + un <= tol:
                    c = _CONF_C
                if dn - un > tol:
                    c = _NONCONF_C
            if c == _NONCONF_C:
                f |= _NONCONF
            elif c == _UNDEC_C:
                f |= _UNDEC
        else:
            f |= _INVALID
        flags[i] = f
        cls[i] = c
    return negative


def kept_point_flags(pred: np.ndarray, U: np.ndarray, cos_i: np.ndarray, cos_v: np.ndarray,
                     grazing_incidence_deg: float, grazing_view_deg: float, X: np.ndarray, lo: np.ndarray,
                     hi: np.ndarray, margin: float, normal_quality: np.ndarray, normal_quality_min: float,
                     tolerance_mm: float, rule: str = "guard_banded", mv_ood: np.ndarray | None = None,
                     shape_ood: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(flags (M,) uint16, decision class (M,) uint8, :data:`NO_DECISION` where d is not finite) of the M kept
    points: ``pred`` and ``U`` (M, 3) mm float64, ``cos_i`` = N·L and ``cos_v`` = N·V (M,), the features ``X``
    (M, F) with the model's range ``lo``/``hi`` (F,) widened by ``margin`` × range, ``normal_quality`` (M,),
    the multivariate (``mv_ood``) and shape (``shape_ood``) out-of-domain masks when the model has them.

    Raises:
        ValueError: ``tolerance_mm`` not > 0, an unknown ``rule``, or a negative U on a point with a finite d.
    """
    if not tolerance_mm > 0:
        raise ValueError(f"tolerance must be > 0, got {tolerance_mm!r}")
    if rule not in fl.DECISION_RULES:
        raise ValueError(f"unknown decision rule {rule!r} (known: {', '.join(fl.DECISION_RULES)})")
    Xc = np.ascontiguousarray(X)
    lo64, hi64 = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    w = (hi64 - lo64) * float(margin)
    lo_m, hi_m = (lo64 - w).astype(Xc.dtype), (hi64 + w).astype(Xc.dtype)
    m = len(pred)
    none = np.zeros(0, np.bool_)
    flags = np.empty(m, np.uint16)
    cls = np.empty(m, np.uint8)
    negative = _kept(np.ascontiguousarray(pred, dtype=np.float64), np.ascontiguousarray(U, dtype=np.float64),
                     np.ascontiguousarray(cos_i), np.ascontiguousarray(cos_v),
                     float(np.cos(np.radians(grazing_incidence_deg))), float(np.cos(np.radians(grazing_view_deg))),
                     Xc, lo_m, hi_m, none if mv_ood is None else np.ascontiguousarray(mv_ood, dtype=np.bool_),
                     none if shape_ood is None else np.ascontiguousarray(shape_ood, dtype=np.bool_),
                     np.ascontiguousarray(normal_quality, dtype=np.float32), np.float32(normal_quality_min),
                     float(tolerance_mm), rule == "simple", flags, cls)
    if negative:
        raise ValueError("U must be >= 0")
    return flags, cls


@njit(**_PAR)
def _scatter(idx, pred, U, kept_flags, cls, flags, dev, unc, decisions):  # pragma: no cover - compiled
    for k in prange(flags.shape[0]):  # NaN / no decision where no kept point lands (numpy's full, split)
        for j in range(3):
            dev[k, j] = np.nan
            unc[k, j] = np.nan
        decisions[k] = NO_DECISION
    for r in prange(idx.shape[0]):
        k = idx[r]
        for j in range(3):
            dev[k, j] = pred[r, j]
            unc[k, j] = U[r, j]
        flags[k] |= kept_flags[r]
        decisions[k] = cls[r]
    for k in prange(flags.shape[0]):  # whatever a stage did: no point with a non-finite d and flags 0
        if flags[k] == 0 and not (np.isfinite(dev[k, 0]) and np.isfinite(dev[k, 1]) and np.isfinite(dev[k, 2])):
            flags[k] = _INVALID


def scatter_kept(n: int, idx: np.ndarray, pred: np.ndarray, U: np.ndarray, kept_flags: np.ndarray,
                 cls: np.ndarray, flags: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(deviations (n, 3), U (n, 3), decisions (n,)) in the cloud's order from the kept points' ``pred``, ``U``
    (M, 3) and classes at flat indices ``idx`` (M,) (distinct), NaN / :data:`NO_DECISION` elsewhere; ``flags``
    (n,) uint16 gets the kept points' flags OR-ed in place, and INVALID_POINT on any point left with a non-finite
    deviation and no flag."""
    idx = np.ascontiguousarray(idx, dtype=np.int64)
    if len(idx) and (idx.min() < 0 or idx.max() >= n):
        raise ValueError(f"kept point index outside the cloud's {n} points")
    dev = np.empty((n, 3))
    unc = np.empty((n, 3))
    decisions = np.empty(n, dtype=np.uint8)
    _scatter(idx, np.ascontiguousarray(pred, dtype=np.float64), np.ascontiguousarray(U, dtype=np.float64),
             np.ascontiguousarray(kept_flags, dtype=np.uint16), np.ascontiguousarray(cls, dtype=np.uint8), flags, dev,
             unc, decisions)
    return dev, unc, decisions


def warm_up() -> None:
    """Compile (or load from numba's cache) both kernels for the types the judge uses."""
    p = np.zeros((2, 3))
    for ct in (np.float32, np.float64):
        f, c = kept_point_flags(p, p, np.ones(2, ct), np.ones(2, ct), 75.0, 75.0, np.zeros((2, 2), np.float32),
                                np.zeros(2), np.ones(2), 0.1, np.ones(2, np.float32), 0.5, 0.1,
                                mv_ood=np.zeros(2, bool), shape_ood=np.zeros(2, bool))
        kept_point_flags(p, p, np.ones(2, ct), np.ones(2, ct), 75.0, 75.0, np.zeros((2, 2), np.float32), np.zeros(2),
                         np.ones(2), 0.1, np.ones(2, np.float32), 0.5, 0.1, rule="simple")
    scatter_kept(3, np.arange(2), p, p, f, c, np.zeros(3, np.uint16))
    for dt in (np.float32, np.float64):
        fin, out, _ = point_masks(np.zeros((2, 3), dt), 1.0)
    base_flags(fin, out, np.zeros(1, np.int64))
