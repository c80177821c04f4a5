"""The profile calibration campaign file (YAML, ``format: xmetro-profile-campaign/1``): a profilometer known only
from its data, one certified sphere, and recordings of single profiles of it. Lengths mm, sensor frame.

Schema (docs/real-data.md gives the shipped example)::

    format: xmetro-profile-campaign/1
    scanner:
      id: profiler-a                  # recorded in the model card
      serial: SN-17
    artifact:                         # the certified sphere every profile shows
      id: sphere_r19
      diameter_mm: 38.1               # or radius_mm
      size_uncertainty_mm: 0.001      # optional, expanded (k = 2)
      certificate: "..."
    profiles:                         # one or more lists of profile files (scan.profiles: CSV / .npy / .npz)
      - list: train_file.txt          # one relative path per line; relative to this file (or absolute)
        root: .                       # optional: the folder the list's paths are relative to (default: its own)
    border_angle_deg: 66              # optional: in-plane normal angle beyond which arc points are border

Repeats of one position (``<position>_<repeat>`` names) are never split between the model's training and U's
calibration folds (see ``learn.profile_model``). Every error names the file and the entry.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from ..preprocess.profile_arc import ARC_MAX_ANGLE_DEG
from .campaign_file import ArtifactSpec, CampaignError, _artifact

__all__ = ["PROFILE_CAMPAIGN_FORMAT", "ProfileCampaign", "ProfileList", "campaign_format", "load_profile_campaign"]

PROFILE_CAMPAIGN_FORMAT = "xmetro-profile-campaign/1"


@dataclass(frozen=True)
class ProfileList:
    """One list file of profiles and the folder its paths are relative to."""

    list_file: Path
    root: Path


@dataclass
class ProfileCampaign:
    """A loaded, checked profile campaign."""

    path: Path
    sha256: str
    scanner_id: str
    scanner_serial: str
    artifact: ArtifactSpec
    lists: list[ProfileList]
    border_angle_deg: float = ARC_MAX_ANGLE_DEG

    def card(self) -> dict[str, Any]:
        """What the model card records of the campaign."""
        return {"format": PROFILE_CAMPAIGN_FORMAT, "file": self.path.name, "sha256": self.sha256,
                "scanner": {"id": self.scanner_id, "serial": self.scanner_serial},
                "artifact": self.artifact.to_dict(), "border_angle_deg": self.border_angle_deg,
                "lists": [str(p.list_file.name) for p in self.lists]}


def _read_yaml(path: Path) -> tuple[dict[str, Any], bytes]:
    try:
        raw = path.read_bytes()
        doc = yaml.safe_load(raw)
    except OSError as e:
        raise CampaignError(f"cannot read the campaign file {path}: {e}") from e
    except yaml.YAMLError as e:
        raise CampaignError(f"{path}: not valid YAML: {e}") from e
    if not isinstance(doc, dict):
        raise CampaignError(f"{path}: a campaign file is a YAML mapping")
    return doc, raw


def campaign_format(path: str | Path) -> str:
    """The ``format`` a campaign file declares (CampaignError when it cannot be read)."""
    doc, _ = _read_yaml(Path(path))
    return str(doc.get("format", ""))


def load_profile_campaign(path: str | Path) -> ProfileCampaign:
    """Read and check a profile campaign file (module doc)."""
    p = Path(path)
    doc, raw = _read_yaml(p)
    where = str(p)
    if doc.get("format") != PROFILE_CAMPAIGN_FORMAT:
        raise CampaignError(f"{where}: format must be {PROFILE_CAMPAIGN_FORMAT!r}, got {doc.get('format')!r}")
    sc = doc.get("scanner") or {}
    if not isinstance(sc, dict) or not str(sc.get("id", "")).strip():
        raise CampaignError(f"{where}: scanner.id is required")
    art_doc = doc.get("artifact")
    if not isinstance(art_doc, dict):
        raise CampaignError(f"{where}: 'artifact' (the certified sphere) is required")
    art = _artifact(art_doc, where)
    if not isinstance(art, ArtifactSpec):
        raise CampaignError(f"{where}: the artifact of a profile campaign is one sphere")
    entries = doc.get("profiles")
    if not isinstance(entries, list) or not entries:
        raise CampaignError(f"{where}: 'profiles' must list at least one {{list: FILE}}")
    lists = []
    for i, e in enumerate(entries):
        if not isinstance(e, dict) or "list" not in e:
            raise CampaignError(f"{where}: profiles[{i}] must be a mapping with 'list'")
        lf = (p.parent / str(e["list"])).resolve()
        if not lf.is_file():
            raise CampaignError(f"{where}: profiles[{i}]: the list file {lf} does not exist")
        root = (p.parent / str(e["root"])).resolve() if e.get("root") is not None else lf.parent
        if not root.is_dir():
            raise CampaignError(f"{where}: profiles[{i}]: root {root} is not a folder")
        lists.append(ProfileList(lf, root))
    try:
        border = float(doc.get("border_angle_deg", ARC_MAX_ANGLE_DEG))
    except (TypeError, ValueError):
        raise CampaignError(f"{where}: border_angle_deg must be a number") from None
    if not 0.0 < border < 90.0:
        raise CampaignError(f"{where}: border_angle_deg must be in (0, 90), got {border:g}")
    return ProfileCampaign(path=p, sha256=hashlib.sha256(raw).hexdigest(), scanner_id=str(sc["id"]),
                           scanner_serial=str(sc.get("serial", "")), artifact=art, lists=lists,
                           border_angle_deg=border)
