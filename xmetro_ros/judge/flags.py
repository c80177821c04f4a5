"""Per-point flag bits and the scan verdict rules (ROS-free).

Flag bits are those of ``ScanQuality.FLAG_*`` (the ``flags`` field of ``~/deviations``):

====  =====================  =====================================================================================
bit   name                   set when
====  =====================  =====================================================================================
1     outlier                removed by statistical outlier removal (no prediction for it)
2     grazing_incidence      incidence angle acos(N·L) > ``grazing_incidence_deg`` (N·L <= 0: not lit at all)
4     grazing_view           view angle acos(N·V) > ``grazing_view_deg`` (N·V <= 0: not seen at all)
8     over_tolerance         predicted |error| (norm over x, y, z) > ``tolerance``
16    out_of_domain          the point lies outside the model's domain for at least one reason, each with its own
                             bit below: domain_features, domain_multivariate, domain_shape (the reasons differ in
                             what they do to U)
32    unreliable_normal      normal quality < ``normal_quality_min`` (quality from the normal estimation, 0..1)
64    invalid_point          x, y or z NaN / Inf (no return) — no prediction for it; also any point whose
                             prediction is not finite for another reason (a point has a finite prediction or a flag)
128   out_of_volume          finite x, y, z outside the working volume (|coordinate| > ``working_volume``,
                             non-physical, e.g. 3e38 m) — treated as no return, no prediction for it
256   non_conforming         ISO 14253-1 decision (:func:`point_decisions`): non-conformance proved,
                             |d| − U > tolerance ("simple" rule: |d| > tolerance)
512   undecided              neither conformance nor non-conformance proved (guard-banded rule only), or a
                             predicted point without a finite U
1024  no_uncertainty         a predicted point without a finite U: the model set has no calibration (every point),
                             or the model gave no spread for it
2048  domain_features        why out_of_domain is set (with it): a feature outside its training range widened by
                             ``domain_margin`` × the range width (ModelSet.domain). U is not widened for this
                             reason (only where the point is also domain_multivariate)
4096  domain_multivariate    why out_of_domain is set (with it): the multivariate domain distance (card
                             ``domain_mv``) exceeds 1 + ``domain_margin``. U is widened: multiplied by the distance
8192  domain_shape           why out_of_domain is set (with it): the surface's shape lies outside the calibration
                             shapes (card ``domain_shape``): its (κmin, κmax) in none of the calibration's cells when
                             the card has them, else its mean curvature outside their range widened by
                             ``domain_margin`` × range, e.g. a concave pocket or a sharp edge; organized scans only.
                             U is not widened: the interval is not vouched for
====  =====================  =====================================================================================

Decision classes (:func:`point_decisions`): per predicted point, on the norm |d| of the predicted error with
U_norm = √(Ux² + Uy² + Uz²) (if each axis' error lies within ±U_i, the error vector lies within U_norm of d, so
the true |error| lies in |d| ± U_norm): conforming (|d| + U_norm ≤ tolerance), non-conforming
(|d| − U_norm > tolerance), undecided otherwise (guard-banded, the default); "simple": |d| ≤ tolerance
conforming, else non-conforming. Conforming points carry no decision bit.

Verdict (:func:`verdict`), fractions taken over the *valid* (finite) points so that the empty cells of an organized
scan do not count against it:

- ERROR: the scan could not be processed (decided by the caller: error code set).
- RESCAN: ``usable / valid < rescan_usable_fraction`` or ``non_conforming / valid > rescan_over_tolerance_fraction``
  or fewer than ``min_valid_points`` valid points.
- WARN: ``flagged / valid > warn_flagged_fraction``, or ``undecided / valid > warn_flagged_fraction``, or the
  settings were defaulted, or the cloud was decimated.
- OK otherwise.

"flagged" and "usable" count the quality bits only (1 to 64: :data:`QUALITY_BITS`): a decision bit says what the
point shows about the part, not that the point is unfit; non-conforming and undecided points act through their own
fractions above. no_uncertainty is not a quality bit either: without a calibration every predicted point is
undecided (guard-banded: WARN, the message says why) and the simple rule works as before. Under the "simple" rule
non-conforming = over tolerance, which is the rule before uncertainty was published.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "CONFORMING",
    "DECISION_NAMES",
    "DECISION_RULES",
    "DOMAIN_REASONS",
    "DOMAIN_REASON_BITS",
    "FLAG_BITS",
    "FLAG_DOMAIN_FEATURES",
    "FLAG_DOMAIN_MULTIVARIATE",
    "FLAG_DOMAIN_SHAPE",
    "FLAG_GRAZING_INCIDENCE",
    "FLAG_GRAZING_VIEW",
    "FLAG_INVALID_POINT",
    "FLAG_NAMES",
    "FLAG_NON_CONFORMING",
    "FLAG_NO_UNCERTAINTY",
    "FLAG_OUTLIER",
    "FLAG_OUT_OF_DOMAIN",
    "FLAG_OUT_OF_VOLUME",
    "FLAG_OVER_TOLERANCE",
    "FLAG_UNDECIDED",
    "FLAG_UNRELIABLE_NORMAL",
    "NON_CONFORMING",
    "QUALITY_BITS",
    "UNDECIDED",
    "VERDICT_ERROR",
    "VERDICT_NAMES",
    "VERDICT_OK",
    "VERDICT_RESCAN",
    "VERDICT_WARN",
    "VerdictThresholds",
    "angle_flags",
    "decision_classes",
    "domain_flags",
    "flag_breakdown",
    "flag_counts",
    "point_decisions",
    "verdict",
    "verdict_name",
]

FLAG_OUTLIER = 1
FLAG_GRAZING_INCIDENCE = 2
FLAG_GRAZING_VIEW = 4
FLAG_OVER_TOLERANCE = 8
FLAG_OUT_OF_DOMAIN = 16
FLAG_UNRELIABLE_NORMAL = 32
FLAG_INVALID_POINT = 64
FLAG_OUT_OF_VOLUME = 128
FLAG_NON_CONFORMING = 256
FLAG_UNDECIDED = 512
FLAG_NO_UNCERTAINTY = 1024
# The reasons for OUT_OF_DOMAIN, each set together with it (detail bits, not quality bits: OUT_OF_DOMAIN counts once)
FLAG_DOMAIN_FEATURES = 2048
FLAG_DOMAIN_MULTIVARIATE = 4096
FLAG_DOMAIN_SHAPE = 8192

FLAG_BITS = (FLAG_OUTLIER, FLAG_GRAZING_INCIDENCE, FLAG_GRAZING_VIEW, FLAG_OVER_TOLERANCE, FLAG_OUT_OF_DOMAIN,
             FLAG_UNRELIABLE_NORMAL, FLAG_INVALID_POINT, FLAG_OUT_OF_VOLUME, FLAG_NON_CONFORMING, FLAG_UNDECIDED,
             FLAG_NO_UNCERTAINTY, FLAG_DOMAIN_FEATURES, FLAG_DOMAIN_MULTIVARIATE, FLAG_DOMAIN_SHAPE)
FLAG_NAMES = ("outlier", "grazing_incidence", "grazing_view", "over_tolerance", "out_of_domain",
              "unreliable_normal", "invalid_point", "out_of_volume", "non_conforming", "undecided", "no_uncertainty",
              "domain_features", "domain_multivariate", "domain_shape")
#: The reasons for OUT_OF_DOMAIN, each its own bit, and their union.
DOMAIN_REASONS = (FLAG_DOMAIN_FEATURES, FLAG_DOMAIN_MULTIVARIATE, FLAG_DOMAIN_SHAPE)
DOMAIN_REASON_BITS = FLAG_DOMAIN_FEATURES | FLAG_DOMAIN_MULTIVARIATE | FLAG_DOMAIN_SHAPE
#: Bits that make a point unfit ("flagged", not "usable" in the verdict); the decision bits are not among them.
QUALITY_BITS = (FLAG_OUTLIER | FLAG_GRAZING_INCIDENCE | FLAG_GRAZING_VIEW | FLAG_OVER_TOLERANCE | FLAG_OUT_OF_DOMAIN
                | FLAG_UNRELIABLE_NORMAL | FLAG_INVALID_POINT | FLAG_OUT_OF_VOLUME)

VERDICT_OK, VERDICT_WARN, VERDICT_RESCAN, VERDICT_ERROR = 0, 1, 2, 3

# ISO 14253-1 decision classes of a point (see decision_classes).
CONFORMING, NON_CONFORMING, UNDECIDED = 0, 1, 2
DECISION_NAMES = ("conforming", "non_conforming", "undecided")
DECISION_RULES = ("guard_banded", "simple")
VERDICT_NAMES = ("OK", "WARN", "RESCAN", "ERROR")


def verdict_name(code: int) -> str:
    """The name of a verdict code (``ScanQuality.VERDICT_*``); ``"?"`` for a code out of range."""
    return VERDICT_NAMES[code] if 0 <= int(code) < len(VERDICT_NAMES) else "?"



@dataclass(frozen=True)
class VerdictThresholds:
    """Thresholds of the verdict rules (fractions of the valid points)."""

    warn_flagged_fraction: float = 0.25
    rescan_usable_fraction: float = 0.5
    rescan_over_tolerance_fraction: float = 0.05
    min_valid_points: int = 100


def flag_counts(flags: np.ndarray) -> list[int]:
    """Number of points with each flag bit set, in bit order."""
    f = np.asarray(flags, dtype=np.uint16).reshape(-1)
    if len(f) == 0:
        return [0] * len(FLAG_BITS)
    # One pass: histogram of the flag words, then per bit the sum over the words that have it.
    hist = np.bincount(f, minlength=int(f.max()) + 1)
    words = np.arange(len(hist))
    return [int(hist[(words & b) != 0].sum()) for b in FLAG_BITS]


def angle_flags(normals: np.ndarray, L: np.ndarray, V: np.ndarray, grazing_incidence_deg: float,
                grazing_view_deg: float, cos_i: np.ndarray | None = None, cos_v: np.ndarray | None = None
                ) -> np.ndarray:
    """GRAZING_INCIDENCE / GRAZING_VIEW bits for (M,) points from unit normals and unit L, V (M, 3)
    (``cos_i`` = N·L, ``cos_v`` = N·V when already computed)."""
    if cos_i is None:
        cos_i = np.einsum("ij,ij->i", normals, L)
    if cos_v is None:
        cos_v = np.einsum("ij,ij->i", normals, V)
    out = np.zeros(len(normals), dtype=np.uint16)
    out[cos_i < np.cos(np.radians(grazing_incidence_deg))] |= FLAG_GRAZING_INCIDENCE
    out[cos_v < np.cos(np.radians(grazing_view_deg))] |= FLAG_GRAZING_VIEW
    return out


def domain_flags(X: np.ndarray, lo: np.ndarray, hi: np.ndarray, margin: float) -> np.ndarray:
    """OUT_OF_DOMAIN and DOMAIN_FEATURES bits for rows of ``X`` (M, F) outside [lo − m·(hi−lo), hi + m·(hi−lo)] in
    any feature."""
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    w = (hi - lo) * float(margin)
    lo_m = (lo - w).astype(X.dtype)
    hi_m = (hi + w).astype(X.dtype)
    m = X < lo_m
    m |= X > hi_m
    out = np.zeros(len(X), dtype=np.uint16)
    if 0 < m.shape[1] < 256:
        # "any over the row" as a uint8 matrix-vector product: ~2x faster than any(axis=1) on few columns
        out[(m.view(np.uint8) @ np.ones(m.shape[1], np.uint8)) > 0] = FLAG_OUT_OF_DOMAIN | FLAG_DOMAIN_FEATURES
    else:
        out[m.any(axis=1)] = FLAG_OUT_OF_DOMAIN | FLAG_DOMAIN_FEATURES
    return out


def decision_classes(d: np.ndarray, U: np.ndarray, tol: float | np.ndarray, rule: str = "guard_banded"
                     ) -> np.ndarray:
    """ISO 14253-1 decision per point (uint8: CONFORMING 0, NON_CONFORMING 1, UNDECIDED 2).

    Args:
        d: predicted error per point, mm, (M,) or (M, A) (per axis; the caller picks what it judges: an axis, or
            the norm over the axes with its U).
        U: expanded uncertainty (95 %) of ``d``, mm, same shape (>= 0; NaN → UNDECIDED under "guard_banded").
        tol: tolerance on the measurement error, mm (> 0), scalar or broadcastable to ``d``.
        rule: "guard_banded" (ISO 14253-1 default: conformance proved only when |d| + U <= tol, non-conformance
            only when |d| − U > tol, undecided in between), or "simple" (simple acceptance, ILAC-G8 / ISO 14253-5
            "shared risk": |d| <= tol conforming, else non-conforming; U not used).

    A non-finite ``d`` is UNDECIDED under both rules (nothing can be proved about it).
    """
    d = np.abs(np.asarray(d, dtype=np.float64))
    tol_a = np.asarray(tol, dtype=np.float64)
    if np.any(~(tol_a > 0)):
        raise ValueError(f"tolerance must be > 0, got {tol!r}")
    out = np.full(d.shape, UNDECIDED, dtype=np.uint8)
    if rule == "simple":
        ok = np.isfinite(d)
        out[ok & (d <= tol_a)] = CONFORMING
        out[ok & (d > tol_a)] = NON_CONFORMING
        return out
    if rule != "guard_banded":
        raise ValueError(f"unknown decision rule {rule!r} (known: {', '.join(DECISION_RULES)})")
    U = np.asarray(U, dtype=np.float64)
    if np.any(U < 0):
        raise ValueError("U must be >= 0")
    U = np.broadcast_to(U, d.shape)
    # NaN compares False: a point without a finite d or U stays UNDECIDED.
    out[d + U <= tol_a] = CONFORMING
    out[d - U > tol_a] = NON_CONFORMING
    return out


def point_decisions(d: np.ndarray, U: np.ndarray, tol: float, rule: str = "guard_banded") -> np.ndarray:
    """Decision class per point (uint8, :data:`CONFORMING` ...) on the error norm (see the module docstring).

    Args:
        d: (M, 3) predicted error, mm. U: (M, 3) expanded uncertainty per axis, mm (NaN: unknown).
        tol: tolerance on |error|, mm. rule: "guard_banded" | "simple".
    """
    d = np.asarray(d, dtype=np.float64)
    U = np.asarray(U, dtype=np.float64)
    dn = np.sqrt(np.einsum("ij,ij->i", d, d))
    un = np.sqrt(np.einsum("ij,ij->i", U, U))
    return decision_classes(dn, un, tol, rule)


def flag_breakdown(counts: list[int], n_valid: int, min_share: float = 0.05) -> str:
    """Which quality flags make a scan's points unfit, for its verdict message: each quality bit set on at least
    ``min_share`` of the ``n_valid`` valid points, most frequent first, as "name share", out_of_domain with its
    reasons in parentheses; ``counts`` as :func:`flag_counts` (in :data:`FLAG_BITS` order). INVALID_POINT and
    OUT_OF_VOLUME are left out (the empty cells of an organized scan carry them); '' when none reaches the share."""
    if n_valid <= 0:
        return ""
    by_bit = dict(zip(FLAG_BITS, counts, strict=True))
    name = dict(zip(FLAG_BITS, FLAG_NAMES, strict=True))

    def items(bits: list[int]) -> list[str]:  # most frequent first, "name share"
        out = []
        for b in sorted(bits, key=lambda b: -by_bit[b]):
            pct = 100 * by_bit[b] / n_valid
            out.append(f"{name[b]} {pct:.0f} %" if pct >= 1 else f"{name[b]} <1 %")
            if b == FLAG_OUT_OF_DOMAIN and any(by_bit[r] for r in DOMAIN_REASONS):
                out[-1] += " (" + ", ".join(items([r for r in DOMAIN_REASONS if by_bit[r]])) + ")"
        return out

    return ", ".join(items([b for b in FLAG_BITS if b & QUALITY_BITS and b not in (FLAG_INVALID_POINT,
                                                                                     FLAG_OUT_OF_VOLUME)
                            and by_bit[b] >= min_share * n_valid]))


def verdict(n_valid: int, n_usable: int, n_flagged: int, n_over_tolerance: int, th: VerdictThresholds,
            settings_defaulted: bool = False, decimated: bool = False, n_undecided: int = 0,
            flags_why: str = "") -> tuple[int, str]:
    """Verdict code and a short reason from the point counts (see the module docstring).

    ``n_over_tolerance`` is the count of non-conforming points (= over tolerance under the "simple" rule);
    ``flags_why`` (:func:`flag_breakdown`) follows the usable or flagged fraction when that decides."""
    why = f" (flags: {flags_why})" if flags_why else ""
    if n_valid < th.min_valid_points:
        return VERDICT_RESCAN, f"only {n_valid} valid points (< {th.min_valid_points})"
    usable = n_usable / n_valid
    over = n_over_tolerance / n_valid
    if usable < th.rescan_usable_fraction:
        return VERDICT_RESCAN, f"usable fraction {usable:.3f} < {th.rescan_usable_fraction:g}{why}"
    if over > th.rescan_over_tolerance_fraction:
        return VERDICT_RESCAN, f"non-conforming fraction {over:.3f} > {th.rescan_over_tolerance_fraction:g}"
    reasons = []
    if n_undecided / n_valid > th.warn_flagged_fraction:
        reasons.append(f"undecided fraction {n_undecided / n_valid:.3f} > {th.warn_flagged_fraction:g}")
    if n_flagged / n_valid > th.warn_flagged_fraction:
        reasons.append(f"flagged fraction {n_flagged / n_valid:.3f} > {th.warn_flagged_fraction:g}{why}")
    if settings_defaulted:
        reasons.append("settings defaulted")
    if decimated:
        reasons.append("cloud decimated")
    if reasons:
        return VERDICT_WARN, "; ".join(reasons)
    return VERDICT_OK, "ok"
