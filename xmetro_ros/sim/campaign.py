"""The study's simulated campaign: 3 spheres x 27 configurations (+ cylinder, + optional plane), seeded per item.

Head poses ("train where you search"): by default every scan looks straight down (the study's set-up). With
``poses`` the campaign also scans from tilted / turned heads, the orientations the rescan recommender explores
(``pose_grid()`` = ``scan.geometry.orientation_grid`` with the recommender's defaults: tilts of ±15° about head X and
Y, turns of ±90° about
head Z), each rotation applied to the looking-down start pose about the top of the artifact (``campaign_pose``),
as the recommender turns the head about a region. A training profile uses it through its campaign arguments, e.g.
``campaign={"sphere_diameters": (35, 45, 55), "cylinder": True, "poses": pose_grid(), "pose_mode": "cycle"}``
(``cycle``: one pose per item, cycling through the grid, so the campaign keeps its 108 scans; ``all``: every item
at every pose, 27× more scans).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..scan.artifacts import Artifact, Cylinder, Plane, Sphere
from ..scan.geometry import HeadPose, orientation_grid
from ..scan.scan import Scan
from ..scan.scanner import ScannerModel, ScanSettings
from .effects import EFFECTS, resolve_effects
from .scanner_sim import DEFAULT_EXTENT_MM, _bounds_corners, scan_grid, simulate_scan

__all__ = ["CYLINDER_RADIUS_MM", "CampaignItem", "campaign_manifest", "campaign_pose", "item_seed", "pose_grid",
           "study_campaign"]

CYLINDER_RADIUS_MM = 20.0


def pose_grid(max_tilt: float = 0.2618, tilt_steps: int = 3, max_turn: float = 1.5708,
              turn_steps: int = 3) -> list[np.ndarray]:
    """Head-frame rotations (3x3) of the recommender's search grid (``scan.geometry.orientation_grid``, which
    ``plan.recommend`` searches; defaults: its
    defaults, 27 rotations, identity included): tilts about head X and Y in ±``max_tilt``, turns about head Z in
    ±``max_turn`` (radians)."""
    return orientation_grid(max_tilt, tilt_steps, max_turn, turn_steps)


def campaign_pose(artifact: Artifact, rotation: np.ndarray, scanner: ScannerModel,
                  extent_mm: float = DEFAULT_EXTENT_MM) -> HeadPose:
    """Start pose of a scan of ``artifact`` with the head turned by ``rotation`` (head frame) about the top of the
    artifact (the surface point straight below the centre of its bounds): the looking-down start pose of
    ``simulate_scan`` rotated about that pivot, so the pivot keeps its stand-off and the scan still starts before
    the artifact along the (rotated) scan direction."""
    base = scan_grid(artifact, scanner.study_configurations()[0], scanner, None, extent_mm).pose
    c = _bounds_corners(artifact, extent_mm).mean(axis=0)
    top = c[2] + scanner.standoff_mm
    depth = artifact.intersect(np.array([[c[0], c[1], top]]), np.array([[0.0, 0.0, -1.0]]))[0]
    pivot = np.array([c[0], c[1], top - depth]) if np.isfinite(depth) else c
    return base.rotated(np.asarray(rotation, dtype=float), pivot=pivot)


def item_seed(campaign_seed: int, index: int) -> int:
    """Seed of campaign item ``index``: derived from the campaign seed and the index (independent streams)."""
    return int(np.random.SeedSequence([int(campaign_seed), int(index)]).generate_state(1)[0])


@dataclass
class CampaignItem:
    """One scan of the campaign, simulated on demand with ``simulate()``."""

    index: int
    artifact: Artifact
    settings: ScanSettings
    config_index: int
    seed: int
    scanner: ScannerModel
    effects: dict[str, Any] | None = None
    extent_mm: float = DEFAULT_EXTENT_MM
    stamp_ns: int = 0
    tags: dict[str, Any] = field(default_factory=dict)
    pose: HeadPose | None = None  # start pose; None → simulate_scan's looking-down default
    pose_index: int | None = None  # index into the campaign's pose grid

    def simulate(self) -> Scan:
        scan = simulate_scan(
            self.artifact,
            self.settings,
            scanner=self.scanner,
            pose=self.pose,
            effects=self.effects,
            seed=self.seed,
            stamp_ns=self.stamp_ns,
            extent_mm=self.extent_mm,
        )
        scan.meta.update({"item": self.index, "config_index": self.config_index, **self.tags})
        if self.pose_index is not None:
            scan.meta["pose_index"] = self.pose_index
        return scan

    def describe(self) -> dict[str, Any]:
        pose = {} if self.pose is None else {
            "pose": {"position_mm": [float(x) for x in self.pose.position],
                     "quaternion_xyzw": [float(x) for x in self.pose.quaternion]},
            "pose_index": self.pose_index,
        }
        return {
            **pose,
            "index": self.index,
            "artifact": self.artifact.to_dict(),
            "config_index": self.config_index,
            "settings": {
                "lateral_density": self.settings.lateral_density,
                "direction_density": self.settings.direction_density,
                "exposure_ms": self.settings.exposure_ms,
            },
            "seed": self.seed,
            "stamp_ns": self.stamp_ns,
        }


def study_campaign(
    scanner: ScannerModel | None = None,
    seed: int = 0,
    sphere_diameters: tuple[float, ...] = (35.0, 45.0, 55.0),
    cylinder: bool = True,
    plane: bool = False,
    effects: dict[str, Any] | None = None,
    configurations: list[ScanSettings] | None = None,
    artifacts: list[Artifact] | None = None,
    poses: list[np.ndarray] | None = None,
    pose_mode: str = "cycle",
    pose_cycles: int = 1,
) -> list[CampaignItem]:
    """Items of the study campaign: each artifact (spheres of ``sphere_diameters`` mm centred at the origin, then
    a cylinder of radius 20 mm with its axis along Y, then optionally the z = 0 plane) x each configuration
    (default: the scanner's 27 study configurations). ``artifacts`` replaces that list when given.

    ``poses``: head-frame rotations (e.g. ``pose_grid()``) applied with ``campaign_pose``; None → looking down
    (the items and seeds of earlier versions). ``pose_mode`` "cycle": item k of an artifact takes pose
    (k + artifact index) mod P (the campaign keeps its size, every pose and every configuration is scanned);
    with ``pose_cycles`` n > 1 each configuration is scanned from n poses, (k + artifact index + j P // n) mod P
    for j < n (n times the scans; n = 1 is the campaign of earlier versions, item for item); "all": each
    artifact x pose x configuration.

    Raises ValueError for a non-positive diameter or a bad pose mode, UnknownEffectError / EffectConfigError for
    bad effects (checked up front, not at the first simulate())."""
    scanner = scanner if scanner is not None else ScannerModel.load()
    resolve_effects(scanner.effects, effects)  # fail fast on bad effect config
    if artifacts is None:
        artifacts = []
        for dia in sphere_diameters:
            if not (isinstance(dia, (int, float)) and np.isfinite(dia) and dia > 0):
                raise ValueError(f"sphere diameters must be positive numbers (mm), got {dia!r}")
            artifacts.append(Sphere(float(dia) / 2.0))
        if cylinder:
            artifacts.append(Cylinder(CYLINDER_RADIUS_MM))
        if plane:
            artifacts.append(Plane())
    configs = configurations if configurations is not None else scanner.study_configurations()
    for c in configs:
        scanner.validate_settings(c)
    if pose_mode not in ("cycle", "all"):
        raise ValueError(f"pose_mode must be 'cycle' or 'all', got {pose_mode!r}")
    if not (isinstance(pose_cycles, int) and pose_cycles >= 1) or (poses is not None and pose_cycles > len(poses)):
        raise ValueError(f"pose_cycles must be an integer from 1 to the number of poses, got {pose_cycles!r}")
    items: list[CampaignItem] = []
    for ai, a in enumerate(artifacts):
        starts: list[HeadPose | None] = [None] if poses is None else [campaign_pose(a, r, scanner) for r in poses]
        plan: list[tuple[int | None, int]]
        if poses is None:
            plan = [(None, ci) for ci in range(len(configs))]
        elif pose_mode == "cycle":
            step = len(starts) // pose_cycles
            plan = [((ci + ai + j * step) % len(starts), ci) for j in range(pose_cycles) for ci in range(len(configs))]
        else:
            plan = [(pi, ci) for pi in range(len(starts)) for ci in range(len(configs))]
        for pi, ci in plan:
            k = len(items)
            items.append(
                CampaignItem(
                    index=k,
                    artifact=a,
                    settings=configs[ci],
                    config_index=ci,
                    seed=item_seed(seed, k),
                    scanner=scanner,
                    effects=effects,
                    stamp_ns=1_700_000_000_000_000_000 + k * 1_000_000_000,
                    pose=None if pi is None else starts[pi],
                    pose_index=pi,
                )
            )
    return items


def campaign_manifest(
    items: list[CampaignItem], *, seed: int, effects: dict[str, Any] | None = None, extra: dict[str, Any] | None = None
) -> dict[str, Any]:
    """JSON-serialisable description of a campaign: seed, scanner, effects (enabled, with parameters), items.
    Holds no paths, except a mesh artifact's file (needed to rebuild it)."""
    scanner = items[0].scanner if items else ScannerModel.load()
    fx = resolve_effects(scanner.effects, effects)
    return {
        "generator": "xmetro_ros.sim.campaign",
        "seed": int(seed),
        "scanner": scanner.id,
        "scanner_source": scanner.source,
        "effects": {e.name: dict(e.params) for e in fx},
        "effects_disabled": [n for n in EFFECTS if n not in {e.name for e in fx}],
        "n_items": len(items),
        "items": [it.describe() for it in items],
        **(extra or {}),
    }
