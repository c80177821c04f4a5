"""A calibration campaign's recordings → one scan per (scan, artifact) with its nominal artifact placed, checked
before anything is trained. Lengths in mm, scan frame.

For each recording the scans (read by the caller's ``read_bag``: this core module reads no ROS bag itself) are
matched to the recording's placements (by their scan selection). In a scan that shows several spheres each point
goes to the sphere whose nominal surface is nearest, within ``gate_mm``; the scan is split into one view per
sphere (other points NaN, organized grids kept organized). Centres: a *known* placement keeps its measured
centre; a *fitted* one gets the least-squares centre with the certified radius per scan, and spheres of a ball bar
seen in the same scan are moved along their axis to the calibrated distance (VDI/VDE 2634-2's use of ball bars),
sharing the correction by their fit uncertainty.

Checks (each failure names the recording, the scan and the cause, :class:`~.campaign_file.CampaignError`): the
scans declare their settings (no defaulted settings) and, when they name one, the campaign's scanner id; every
placement is found in the data with enough points; a free-radius fit agrees with the certified radius; the
estimated surface normals agree with the nominal shape (a single laser profile cannot give them: refused with the
reason); every stamp / index a placement lists is a scan of its recording (and a time window selects one at
least); settings levels covered: the levels the campaign file declares (``settings_levels``), else the scanner
description's, must each appear in a scan (an error names the level); when neither declares any, the scans' own
levels are taken as the scanner's; a setting with a single level is noted (its effect cannot be learned).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..scan.artifacts import Sphere
from ..scan.fitting import FitError, fit_sphere, fit_sphere_center
from ..scan.geometry import vec3
from ..scan.scan import Scan
from ..scan.scanner import SETTING_NAMES
from .campaign_file import Campaign, CampaignError, Placement, Recording
from .vdi2634 import SphereFigures, probing, spacing_error

__all__ = ["CampaignData", "CampaignScan", "DataChecks", "assemble"]

#: Points of a scan within this distance (mm) of a sphere's nominal surface belong to it (larger of this and
#: 8 % of the radius: placements and guesses are rough).
GATE_MM = 2.0
#: A sphere seen by fewer points in a scan is not a measurement of it.
MIN_POINTS = 200
#: A free-radius fit further than this from the certified radius (larger of mm and fraction) means the wrong
#: artifact, a wrong certificate or a scan of something else.
RADIUS_TOLERANCE = (0.5, 0.03)
#: Median angle (deg) between estimated and nominal normals above which the normals are not usable.
MAX_NORMAL_ANGLE_DEG = 20.0


@dataclass
class CampaignScan:
    """One sphere in one scan: the view of the scan holding its points, with the nominal sphere placed."""

    recording: int
    index: int  # scan number in its recording
    stamp_ns: int
    placement: Placement
    scan: Scan
    figures: SphereFigures
    fitted_center: tuple[float, float, float] | None = None

    @property
    def label(self) -> str:
        """``recording r scan i (artifact)``: how errors and reports name it."""
        return f"recording {self.recording} scan {self.index} ({self.placement.artifact})"


@dataclass
class DataChecks:
    """What was checked before training (recorded in the model card and the report)."""

    n_scans_read: int = 0
    n_measurements: int = 0
    per_artifact: dict[str, int] = field(default_factory=dict)
    settings_levels: dict[str, list[float]] = field(default_factory=dict)
    levels_from_campaign: bool = False  # True: nothing declared levels, the scans' own are the model's
    levels_source: str = ""  # who declared the checked levels: "campaign file", "scanner description" or "scans"
    min_points: int = 0
    median_normal_angle_deg: float = 0.0
    radius_deviation_max_mm: float = 0.0
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able checks."""
        return dict(self.__dict__)


@dataclass
class CampaignData:
    """The assembled campaign: measurements, checks, VDI/VDE 2634-2 rows and the scanner with its levels."""

    campaign: Campaign
    scans: list[CampaignScan]
    checks: DataChecks
    spacing: list[dict[str, Any]]
    scanner: Any


def _has_level(values: Any, level: float) -> bool:
    """True when ``level`` is one of ``values`` (relative tolerance 1e-6: settings travel as float32 or text)."""
    return any(abs(v - level) <= 1e-6 * max(abs(level), 1e-9) for v in values)


def _gate(radius: float) -> float:
    return max(GATE_MM, 0.08 * radius)


def _median_normal_angle(scan: Scan, sphere: Sphere, scanner: Any) -> float:
    """Median angle (deg) between the estimated normals of the scan's points and the sphere's nominal normals."""
    from ..preprocess import PreprocessConfig, prepare_scan

    prep = prepare_scan(scan, PreprocessConfig(), scanner=scanner)
    if len(prep) == 0:
        return 180.0
    nom = sphere.normals(sphere.project(np.asarray(prep.points, dtype=float)))
    cos = np.clip(np.einsum("ij,ij->i", np.asarray(prep.normals, dtype=float), nom), -1.0, 1.0)
    return float(np.degrees(np.median(np.arccos(cos))))


def _single_profile(scan: Scan) -> str:
    """A reason when the scan is a single laser profile (one row, or all points in one plane), else ""."""
    p = scan.points.reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)]
    if scan.organized and scan.points.shape[0] == 1:
        return "it is a single laser profile (one row)"
    if len(p) >= 3:
        s = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
        if s[-1] < 1e-6 * s[0]:
            return "its points lie in one plane (a single laser profile)"
    return ""


def _split(scan: Scan, spheres: list[Sphere]) -> list[np.ndarray]:
    """Per sphere, a boolean mask (shape of the grid) of the points that belong to it."""
    p = scan.points.reshape(-1, 3)
    ok = np.isfinite(p).all(axis=1)
    dist = np.full((len(spheres), len(p)), np.inf)
    for k, s in enumerate(spheres):
        d = np.abs(np.linalg.norm(p[ok] - s.c, axis=1) - s.radius)
        dist[k, ok] = np.where(d <= _gate(s.radius), d, np.inf)
    best = np.argmin(dist, axis=0)
    found = np.isfinite(dist.min(axis=0))
    shape = scan.points.shape[:-1]
    return [((best == k) & found).reshape(shape) for k in range(len(spheres))]


def _view(scan: Scan, mask: np.ndarray, sphere: Sphere) -> Scan:
    pts = np.where(mask[..., None], scan.points, np.nan)
    return replace(scan, points=pts, artifact=sphere, expected_error=None)


def _apply_ball_bars(items: list[CampaignScan], campaign: Campaign) -> list[dict[str, Any]]:
    """Constrain fitted centres of ball-bar spheres seen in the same scan to the calibrated distance; return the
    spacing rows (SD from the free fits) of every bar seen."""
    rows = []
    by_scan: dict[tuple[int, int], dict[str, CampaignScan]] = {}
    for it in items:
        by_scan.setdefault((it.recording, it.index), {})[it.placement.artifact] = it
    for (rec, idx), seen in sorted(by_scan.items()):
        for bar in campaign.ball_bars:
            a, b = (seen.get(s) for s in bar.spheres)
            if a is None or b is None:
                continue
            rows.append({"recording": rec, "scan": idx, "ball_bar": bar.id,
                         "settings": a.scan.settings.label(),
                         "SD_mm": spacing_error(a.figures, b.figures, bar.distance_mm)})
            if a.fitted_center is None or b.fitted_center is None:
                continue  # known positions are not moved
            ca, cb = np.asarray(a.fitted_center), np.asarray(b.fitted_center)
            axis = cb - ca
            dist = float(np.linalg.norm(axis))
            if dist == 0:
                continue
            axis /= dist
            # Share the correction by the fits' uncertainty (∝ rms / √n).
            wa = a.figures.rms_mm / np.sqrt(a.figures.n_points)
            wb = b.figures.rms_mm / np.sqrt(b.figures.n_points)
            share_a = wa / (wa + wb) if wa + wb > 0 else 0.5
            delta = bar.distance_mm - dist
            ca = ca - axis * delta * share_a
            cb = cb + axis * delta * (1 - share_a)
            for it, c in ((a, ca), (b, cb)):
                it.fitted_center = vec3(c)
                assert isinstance(it.scan.artifact, Sphere)
                it.scan = replace(it.scan, artifact=Sphere(it.scan.artifact.radius, vec3(c)))
    return rows


def assemble(campaign: Campaign, read_bag: Callable[[Recording], list[Scan]], *,
             check_normals: bool = True, min_points: int = MIN_POINTS, require_levels: bool = True) -> CampaignData:
    """Read every recording (``read_bag``), match scans to placements, place the artifacts, run the checks.

    ``require_levels`` (training, ``xmetro calibrate``): every declared settings level must be in a scan. False for
    uses that train nothing over the levels (``xmetro loop`` on reference scans): uncovered levels are only noted.

    Raises:
        CampaignError: naming the recording, the scan and the cause.
    """
    scanner = campaign.scanner
    items: list[CampaignScan] = []
    checks = DataChecks(min_points=min_points)
    settings_seen: set[tuple[float, float, float]] = set()
    angles: list[float] = []
    for ri, rec in enumerate(campaign.recordings):
        where = f"recording {ri} ({rec.bag.name})"
        try:
            scans = read_bag(rec)
        except (OSError, ValueError, KeyError) as e:
            raise CampaignError(f"{where}: cannot be read: {e}") from e
        if not scans:
            raise CampaignError(f"{where}: holds no scan on {rec.scan_topic}")
        first = min(s.stamp_ns for s in scans)
        stamps = [s.stamp_ns for s in scans]
        for pl in rec.placements:
            why = pl.scans.missing(stamps)
            if why:
                raise CampaignError(f"{where} ({len(scans)} scans on {rec.scan_topic}): placement of artifact "
                                    f"{pl.artifact!r} ({pl.scans.describe()}): {why}")
        for si, scan in enumerate(scans):
            checks.n_scans_read += 1
            sw = f"{where} scan {si} (stamp {scan.stamp_ns} ns)"
            if scan.meta.get("settings_defaulted"):
                raise CampaignError(f"{sw}: no ScannerSettings on {rec.settings_topic} at or before it: a "
                                    "calibration scan must declare its settings")
            if scan.scanner_id and scan.scanner_id != campaign.scanner_id:
                raise CampaignError(f"{sw}: taken by scanner {scan.scanner_id!r}, the campaign is for "
                                    f"{campaign.scanner_id!r}")
            reason = _single_profile(scan)
            if reason:
                raise CampaignError(f"{sw}: {reason}: surface normals, hence the incidence and viewing "
                                    "angles the model learns from, cannot be estimated from one profile. Record "
                                    "scans (several profiles per artifact) instead")
            placements = [pl for pl in rec.placements if pl.scans.selects(si, scan.stamp_ns, first)]
            if not placements:
                continue
            specs = [campaign.artifacts[pl.artifact] for pl in placements]
            guesses = [Sphere(sp.radius_mm, pl.center_hint) for sp, pl in zip(specs, placements, strict=True)]
            masks = _split(scan, guesses)
            for pl, sp, guess, mask in zip(placements, specs, guesses, masks, strict=True):
                pw = f"{sw}: artifact {pl.artifact!r}"
                n = int(mask.sum())
                if n < min_points:
                    raise CampaignError(f"{pw} not found: {n} points within {_gate(sp.radius_mm):.1f} mm of its "
                                        f"nominal surface around {pl.center_hint} (need {min_points})")
                pts = scan.points[mask]
                try:
                    _c_free, r_free, _rms = fit_sphere(pts)
                except (FitError, ValueError) as e:
                    raise CampaignError(f"{pw}: sphere fit failed: {e}") from e
                tol = max(RADIUS_TOLERANCE[0], RADIUS_TOLERANCE[1] * sp.radius_mm)
                dev = float(r_free - sp.radius_mm)
                if abs(dev) > tol:
                    raise CampaignError(f"{pw}: the points fit a sphere of radius {r_free:.3f} mm, the certified "
                                        f"radius is {sp.radius_mm:.4f} mm (|difference| > {tol:.2f} mm): wrong "
                                        "artifact, wrong certificate or a scan of something else")
                checks.radius_deviation_max_mm = max(checks.radius_deviation_max_mm, abs(dev))
                fitted = None
                if pl.fitted:
                    try:
                        c = fit_sphere_center(pts, sp.radius_mm, init=np.asarray(guess.c))
                    except FitError as e:
                        raise CampaignError(f"{pw}: centre fit failed: {e}") from e
                    fitted = vec3(c)
                    sphere = Sphere(sp.radius_mm, fitted)
                else:
                    sphere = guess
                view = _view(scan, mask, sphere)
                if check_normals:
                    ang = _median_normal_angle(view, sphere, scanner)
                    angles.append(ang)
                    if ang > MAX_NORMAL_ANGLE_DEG:
                        raise CampaignError(f"{pw}: estimated normals are {ang:.0f}° (median) off the sphere's: "
                                            "the points do not describe the surface (single profile, sparse or "
                                            "mis-registered scan)")
                figures = probing(pts, sp.diameter_mm, None if pl.fitted else pl.known)
                items.append(CampaignScan(ri, si, scan.stamp_ns, pl, view, figures, fitted))
                settings_seen.add(scan.settings.as_tuple())
                checks.per_artifact[pl.artifact] = checks.per_artifact.get(pl.artifact, 0) + 1
    missing = sorted(set(campaign.artifacts) - set(checks.per_artifact))
    if missing:
        raise CampaignError(f"campaign {campaign.path.name}: artifacts {missing} were found in no scan")
    levels = {name: sorted({s[k] for s in settings_seen}) for k, name in enumerate(SETTING_NAMES)}
    declared, by = ((campaign.settings_levels, f"the campaign {campaign.path.name}")
                    if campaign.settings_levels is not None else
                    (scanner.settings_levels, f"the scanner description {scanner.source}"))
    if declared is None:
        # Nothing declared (a data sheet gives no levels): the scans' own levels are the model's, by construction
        # all covered; a note says so.
        scanner = scanner.with_levels({k: tuple(v) for k, v in levels.items()})
        checks.levels_from_campaign = True
        checks.levels_source = "scans"
        checks.notes.append("the scanner description gives no settings levels: the campaign's are used")
    else:
        # Declared levels are a promise that the model knows them (the node's recommender searches them): a level
        # no scan shows would be extrapolated, so it stops the run, naming the level.
        uncovered = {k: [v for v in declared[k] if not _has_level(levels[k], v)] for k in SETTING_NAMES}
        uncovered = {k: v for k, v in uncovered.items() if v}
        what = "; ".join(f"{k} = {', '.join(f'{v:g}' for v in vs)}" for k, vs in uncovered.items())
        if uncovered and not require_levels:
            checks.notes.append(f"settings levels declared by {by} in no scan: {what}")
        elif uncovered:
            raise CampaignError(f"campaign {campaign.path.name}: settings levels declared by {by} are in no scan: "
                                f"{what} (the scans show {levels}). Record scans at these levels, or declare the "
                                "levels the campaign covers (settings_levels in the campaign file)")
        checks.levels_source = "campaign file" if campaign.settings_levels is not None else "scanner description"
        if campaign.settings_levels is not None:
            scanner = scanner.with_levels(campaign.settings_levels)
        unknown = {k: [v for v in levels[k] if not _has_level(declared[k], v)] for k in SETTING_NAMES}
        unknown = {k: v for k, v in unknown.items() if v}
        if unknown:
            checks.notes.append(f"settings outside the levels declared by {by}: {unknown}")
    thin = [k for k, v in levels.items() if len(v) < 2]
    if thin:
        checks.notes.append(f"only one level of {thin}: the model cannot learn their effect")
    checks.settings_levels = {k: list(v) for k, v in levels.items()}
    checks.n_measurements = len(items)
    checks.median_normal_angle_deg = float(np.median(angles)) if angles else 0.0
    spacing = _apply_ball_bars(items, campaign)
    return CampaignData(campaign, items, checks, spacing, scanner)
