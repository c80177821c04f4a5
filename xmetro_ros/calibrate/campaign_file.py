"""The calibration campaign file (YAML, ``format: xmetro-campaign/1``): which scanner, which certified artifacts,
and for each recording which artifact each scan shows and where it sits. Lengths in mm, in the scan frame.

Schema (a complete file: config/campaigns/demo_campaign.yaml)::

    format: xmetro-campaign/1
    scanner:
      id: ls-200                      # must equal the recordings' ScannerSettings.scanner_id (when they give one)
      serial: SN-0042
      description: ls-200.yaml        # scanner YAML (model or data-sheet terms), relative to this file
    settings_levels:                  # optional: the levels the campaign covers (each must be scanned); they
      lateral_density: [4.0, 6.0]     # become the model's levels. Without them the description's levels are
      direction_density: [2.0, 3.0]   # checked (each scanned), or, when it has none, the scans' own are used
      exposure_ms: [0.5, 2.0]
    artifacts:
      - id: ball_a
        kind: sphere
        diameter_mm: 25.4003          # certified size (or radius_mm)
        size_uncertainty_mm: 0.0008   # expanded (k = 2) uncertainty of the certified size
        form_mm: 0.0004               # certified form deviation, and its uncertainty
        form_uncertainty_mm: 0.0003
        certificate: "DAkkS D-K-12345 2026-0113"
      - id: bar_ab                    # a ball bar: calibrated centre-to-centre distance of two spheres
        kind: ball_bar
        spheres: [ball_a, ball_b]
        distance_mm: 150.0021
        distance_uncertainty_mm: 0.0012
        certificate: "..."
    recordings:
      - bag: run1                     # rosbag2 directory or bare .mcap, relative to this file
        scan_topic: /scan             # default /scan
        settings_topic: /scanner_settings
        placements:                   # what the scans of this recording show
          - artifact: ball_a
            position: {known: [40.0, -10.0, 0.0], uncertainty_mm: 0.002, source: CMM}
          - artifact: ball_b
            position: {fit: [-60.0, 5.0, 0.0]}      # fitted with the certified size, from this guess
            scans: {from_s: 0.0, to_s: 12.5}       # optional: a window of header stamps (s from the first
                                                   # scan), or {stamps_ns: [...]}, or {indices: [...]};
                                                   # every listed stamp / index must be a scan of the bag

A *known* position (fixture, CMM, laser tracker) keeps every error of the scanner in the targets. A *fitted*
position (certified size fixed, centre fitted per scan) absorbs every error that looks like a shift of the
artifact: location errors are removed from what the model learns (and from what it can predict); ball bars
constrain fitted centres to their calibrated distance. Every error names the file, the recording and the cause.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from ..scan.artifacts import Sphere
from ..scan.scanner import ScannerModel

__all__ = [
    "CAMPAIGN_FORMAT",
    "ArtifactSpec",
    "BallBar",
    "Campaign",
    "CampaignError",
    "Placement",
    "Recording",
    "ScanSelection",
    "load_campaign",
]

CAMPAIGN_FORMAT = "xmetro-campaign/1"


class CampaignError(ValueError):
    """A campaign that cannot be used: the message names the file, the entry (recording, scan) and the cause."""


@dataclass(frozen=True)
class ArtifactSpec:
    """A certified sphere: id, radius (mm) and the certificate's figures (mm, expanded k = 2)."""

    id: str
    radius_mm: float
    size_uncertainty_mm: float = 0.0
    form_mm: float = 0.0
    form_uncertainty_mm: float = 0.0
    certificate: str = ""

    @property
    def diameter_mm(self) -> float:
        """Certified diameter, mm."""
        return 2.0 * self.radius_mm

    def placed(self, center: tuple[float, float, float]) -> Sphere:
        """The nominal sphere at ``center`` (scan frame, mm)."""
        return Sphere(self.radius_mm, center)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able description (for the model card)."""
        return {"id": self.id, "kind": "sphere", "diameter_mm": self.diameter_mm,
                "size_uncertainty_mm": self.size_uncertainty_mm, "form_mm": self.form_mm,
                "form_uncertainty_mm": self.form_uncertainty_mm, "certificate": self.certificate}


@dataclass(frozen=True)
class BallBar:
    """Two spheres with a calibrated centre-to-centre distance (mm, expanded uncertainty k = 2)."""

    id: str
    spheres: tuple[str, str]
    distance_mm: float
    distance_uncertainty_mm: float = 0.0
    certificate: str = ""

    def to_dict(self) -> dict[str, Any]:
        """JSON-able description (for the model card)."""
        return {"id": self.id, "kind": "ball_bar", "spheres": list(self.spheres), "distance_mm": self.distance_mm,
                "distance_uncertainty_mm": self.distance_uncertainty_mm, "certificate": self.certificate}


@dataclass(frozen=True)
class ScanSelection:
    """Which scans of a recording a placement applies to: all, a window of header stamps (seconds from the first
    scan of the recording), explicit header stamps, or indices in recording order."""

    from_s: float | None = None
    to_s: float | None = None
    stamps_ns: tuple[int, ...] | None = None
    indices: tuple[int, ...] | None = None

    def selects(self, index: int, stamp_ns: int, first_stamp_ns: int) -> bool:
        """True when the scan number ``index`` (header stamp ``stamp_ns``) is selected."""
        if self.indices is not None:
            return index in self.indices
        if self.stamps_ns is not None:
            return stamp_ns in self.stamps_ns
        t = (stamp_ns - first_stamp_ns) * 1e-9
        return (self.from_s is None or t >= self.from_s) and (self.to_s is None or t <= self.to_s)

    def describe(self) -> str:
        """How the selection reads in messages (``all scans``, ``indices [...]``, ...)."""
        if self.indices is not None:
            return f"indices {list(self.indices)}"
        if self.stamps_ns is not None:
            return f"stamps_ns {list(self.stamps_ns)}"
        if self.from_s is None and self.to_s is None:
            return "all scans"
        return f"scans from_s {self.from_s} to_s {self.to_s}"

    def missing(self, stamps_ns: list[int]) -> str:
        """Why the selection does not fit a recording whose scans (in recording order) have ``stamps_ns``: the
        listed indices / stamps that match no scan, or a window that selects no scan; "" when it fits."""
        n = len(stamps_ns)
        if self.indices is not None:
            bad = [i for i in self.indices if not 0 <= i < n]
            return f"indices {bad} match no scan (the recording has {n} scans, indices 0-{n - 1})" if bad else ""
        if self.stamps_ns is not None:
            have = set(stamps_ns)
            bad = [s for s in self.stamps_ns if s not in have]
            if bad:
                span = f"{min(stamps_ns)}-{max(stamps_ns)} ns" if stamps_ns else "none"
                return f"stamps_ns {bad} match no scan header stamp (the recording's {n} scans span {span})"
            return ""
        first = min(stamps_ns) if stamps_ns else 0
        if not any(self.selects(i, s, first) for i, s in enumerate(stamps_ns)):
            last = (max(stamps_ns) - first) * 1e-9 if stamps_ns else 0.0
            return (f"the window from_s {self.from_s} to_s {self.to_s} selects no scan (the recording's {n} scans "
                    f"span 0-{last:.3f} s from the first)")
        return ""


@dataclass(frozen=True)
class Placement:
    """An artifact in the scans of a recording: a known centre (with its uncertainty and source) or a centre to
    fit from ``guess`` (scan frame, mm)."""

    artifact: str
    known: tuple[float, float, float] | None = None
    guess: tuple[float, float, float] | None = None
    uncertainty_mm: float = 0.0
    source: str = ""
    scans: ScanSelection = field(default_factory=ScanSelection)

    @property
    def fitted(self) -> bool:
        """True when the centre is fitted (no independent position)."""
        return self.known is None

    @property
    def center_hint(self) -> tuple[float, float, float]:
        """The known centre, or the guess a fit starts from."""
        c = self.known if self.known is not None else self.guess
        assert c is not None  # the loader guarantees one of them
        return c


@dataclass(frozen=True)
class Recording:
    """One recording (bag) of the campaign and what its scans show."""

    bag: Path
    placements: tuple[Placement, ...]
    scan_topic: str = "/scan"
    settings_topic: str = "/scanner_settings"


@dataclass
class Campaign:
    """A loaded, checked campaign file."""

    path: Path
    sha256: str
    scanner_id: str
    scanner_serial: str
    scanner: ScannerModel
    artifacts: dict[str, ArtifactSpec]
    ball_bars: list[BallBar]
    recordings: list[Recording]
    #: The settings levels the campaign declares it covers (optional ``settings_levels`` of the file): every one
    #: must be scanned, and they become the model's scanner levels (over the description's).
    settings_levels: dict[str, tuple[float, ...]] | None = None

    def card(self) -> dict[str, Any]:
        """What a model card records of the campaign (hash, scanner, artifacts and certificates, recordings)."""
        return {"format": CAMPAIGN_FORMAT, "file": self.path.name, "sha256": self.sha256,
                "settings_levels": None if self.settings_levels is None else
                {k: list(v) for k, v in self.settings_levels.items()},
                "scanner": {"id": self.scanner_id, "serial": self.scanner_serial, "description": self.scanner.source},
                "artifacts": [a.to_dict() for a in self.artifacts.values()],
                "ball_bars": [b.to_dict() for b in self.ball_bars],
                "recordings": [{"bag": str(r.bag.name), "placements": [
                    {"artifact": p.artifact, "position": "fitted" if p.fitted else "known",
                     "source": p.source, "uncertainty_mm": p.uncertainty_mm} for p in r.placements]}
                    for r in self.recordings]}


def _num(v: Any, what: str, where: str, positive: bool = False) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise CampaignError(f"{where}: {what} must be a number, got {v!r}") from None
    if not math.isfinite(x) or (positive and x <= 0) or x < 0:
        raise CampaignError(f"{where}: {what} must be a {'positive' if positive else 'non-negative'} number, "
                            f"got {v!r}")
    return x


def _vec(v: Any, what: str, where: str) -> tuple[float, float, float]:
    if not isinstance(v, (list, tuple)) or len(v) != 3:
        raise CampaignError(f"{where}: {what} must be three numbers [x, y, z] (mm), got {v!r}")
    out = tuple(float(x) for x in v)
    if not all(math.isfinite(x) for x in out):
        raise CampaignError(f"{where}: {what} must be finite, got {v!r}")
    return out  # type: ignore[return-value]


def _artifact(d: dict[str, Any], where: str) -> ArtifactSpec | BallBar:
    aid = str(d.get("id", "")).strip()
    if not aid:
        raise CampaignError(f"{where}: an artifact needs an id")
    where = f"{where} artifact {aid!r}"
    kind = str(d.get("kind", "sphere")).lower()
    if kind == "ball_bar":
        spheres = d.get("spheres")
        if not isinstance(spheres, (list, tuple)) or len(spheres) != 2:
            raise CampaignError(f"{where}: a ball bar names exactly two spheres")
        return BallBar(aid, (str(spheres[0]), str(spheres[1])), _num(d.get("distance_mm"), "distance_mm", where, True),
                       _num(d.get("distance_uncertainty_mm", 0.0), "distance_uncertainty_mm", where),
                       str(d.get("certificate", "")))
    if kind != "sphere":
        raise CampaignError(f"{where}: kind {kind!r} is not supported (sphere, ball_bar)")
    if "radius_mm" in d:
        radius = _num(d["radius_mm"], "radius_mm", where, True)
    elif "diameter_mm" in d:
        radius = 0.5 * _num(d["diameter_mm"], "diameter_mm", where, True)
    else:
        raise CampaignError(f"{where}: a sphere needs its certified diameter_mm or radius_mm")
    return ArtifactSpec(aid, radius, _num(d.get("size_uncertainty_mm", 0.0), "size_uncertainty_mm", where),
                        _num(d.get("form_mm", 0.0), "form_mm", where),
                        _num(d.get("form_uncertainty_mm", 0.0), "form_uncertainty_mm", where),
                        str(d.get("certificate", "")))


def _selection(d: Any, where: str) -> ScanSelection:
    if d is None:
        return ScanSelection()
    if not isinstance(d, dict):
        raise CampaignError(f"{where}: scans must be a mapping (from_s / to_s, stamps_ns or indices)")
    unknown = set(d) - {"from_s", "to_s", "stamps_ns", "indices"}
    if unknown:
        raise CampaignError(f"{where}: unknown scan selection keys {sorted(unknown)}")
    try:
        return ScanSelection(
            from_s=float(d["from_s"]) if "from_s" in d else None, to_s=float(d["to_s"]) if "to_s" in d else None,
            stamps_ns=tuple(int(x) for x in d["stamps_ns"]) if "stamps_ns" in d else None,
            indices=tuple(int(x) for x in d["indices"]) if "indices" in d else None)
    except (TypeError, ValueError) as e:
        raise CampaignError(f"{where}: bad scan selection {d!r}: {e}") from None


def _placement(d: Any, artifacts: dict[str, ArtifactSpec], where: str) -> Placement:
    if not isinstance(d, dict) or "artifact" not in d:
        raise CampaignError(f"{where}: a placement needs an artifact")
    aid = str(d["artifact"])
    if aid not in artifacts:
        raise CampaignError(f"{where}: unknown artifact {aid!r} (declared spheres: {sorted(artifacts)})")
    pos = d.get("position")
    where = f"{where} placement of {aid!r}"
    if not isinstance(pos, dict) or (("known" in pos) == ("fit" in pos)):
        raise CampaignError(f"{where}: position must be {{known: [x, y, z], uncertainty_mm: ...}} or "
                            "{fit: [x, y, z] (a starting guess)}")
    sel = _selection(d.get("scans"), where)
    if "known" in pos:
        return Placement(aid, known=_vec(pos["known"], "position.known", where),
                         uncertainty_mm=_num(pos.get("uncertainty_mm", 0.0), "uncertainty_mm", where),
                         source=str(pos.get("source", "")), scans=sel)
    return Placement(aid, guess=_vec(pos["fit"], "position.fit", where), scans=sel)


def _levels(d: Any, where: str) -> dict[str, tuple[float, ...]] | None:
    from ..scan.scanner import SETTING_NAMES

    if d is None:
        return None
    if not isinstance(d, dict) or set(d) != set(SETTING_NAMES):
        raise CampaignError(f"{where}: settings_levels must give the levels of each of {list(SETTING_NAMES)}, got "
                            f"{sorted(d) if isinstance(d, dict) else d!r}")
    out = {}
    for k in SETTING_NAMES:
        v = d[k]
        if not isinstance(v, (list, tuple)) or not v:
            raise CampaignError(f"{where}: settings_levels.{k} must be a non-empty list of numbers, got {v!r}")
        out[k] = tuple(sorted({_num(x, f"settings_levels.{k}", where, True) for x in v}))
    return out


def load_campaign(path: str | Path) -> Campaign:
    """Read and check a campaign file (schema in the module docstring).

    Raises:
        CampaignError: naming the entry and the cause (unknown artifact, missing file, bad number, ...).
    """
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as e:
        raise CampaignError(f"campaign {p}: cannot be read: {e}") from e
    try:
        d = yaml.safe_load(raw)
    except yaml.YAMLError as e:
        raise CampaignError(f"campaign {p}: not valid YAML: {e}") from e
    where = f"campaign {p.name}"
    if not isinstance(d, dict) or d.get("format") != CAMPAIGN_FORMAT:
        raise CampaignError(f"{where}: format must be {CAMPAIGN_FORMAT!r}")
    sc = d.get("scanner") or {}
    if not isinstance(sc, dict) or not sc.get("id") or not sc.get("description"):
        raise CampaignError(f"{where}: scanner needs an id and a description file (scanner YAML)")
    desc = p.parent / str(sc["description"])
    try:
        scanner = ScannerModel.load(desc)
    except (FileNotFoundError, ValueError) as e:
        raise CampaignError(f"{where}: scanner description {desc}: {e}") from e
    if scanner.id != str(sc["id"]):
        raise CampaignError(f"{where}: scanner id {sc['id']!r} differs from its description's id {scanner.id!r}")
    artifacts: dict[str, ArtifactSpec] = {}
    bars: list[BallBar] = []
    for a in d.get("artifacts") or []:
        spec = _artifact(a if isinstance(a, dict) else {}, where)
        if spec.id in artifacts or any(b.id == spec.id for b in bars):
            raise CampaignError(f"{where}: artifact id {spec.id!r} is declared twice")
        if isinstance(spec, BallBar):
            bars.append(spec)
        else:
            artifacts[spec.id] = spec
    if not artifacts:
        raise CampaignError(f"{where}: no certified sphere declared")
    for b in bars:
        for s in b.spheres:
            if s not in artifacts:
                raise CampaignError(f"{where}: ball bar {b.id!r} names unknown sphere {s!r}")
    recordings = []
    for i, r in enumerate(d.get("recordings") or []):
        rw = f"{where} recording {i}"
        if not isinstance(r, dict) or "bag" not in r:
            raise CampaignError(f"{rw}: needs a bag")
        bag = p.parent / str(r["bag"])
        rw = f"{where} recording {i} ({r['bag']})"
        if not bag.exists():
            raise CampaignError(f"{rw}: the bag {bag} does not exist")
        placements = tuple(_placement(x, artifacts, rw) for x in r.get("placements") or [])
        if not placements:
            raise CampaignError(f"{rw}: no placement: say which artifact its scans show")
        recordings.append(Recording(bag, placements, str(r.get("scan_topic", "/scan")),
                                    str(r.get("settings_topic", "/scanner_settings"))))
    if not recordings:
        raise CampaignError(f"{where}: no recordings")
    used = {pl.artifact for r in recordings for pl in r.placements}
    unused = sorted(set(artifacts) - used)
    if unused:
        raise CampaignError(f"{where}: certified artifacts {unused} appear in no recording")
    if scanner.serial and sc.get("serial") and str(sc["serial"]) != scanner.serial:
        raise CampaignError(f"{where}: scanner serial {sc['serial']!r} differs from its description's "
                            f"{scanner.serial!r}")
    return Campaign(p, hashlib.sha256(raw).hexdigest(), scanner.id, str(sc.get("serial", scanner.serial) or ""),
                    scanner, artifacts, bars, recordings, _levels(d.get("settings_levels"), where))
