"""Surfaces for calibrating U beyond the study's spheres and cylinders: plates, grooves and dimples, a saddle and a
filleted ridge, generated in code (deterministic numpy, millimetres, the part frame of
:mod:`xmetro_ros.scan.generated_parts`: the scanner 90 mm above the origin looking down −Z).

Parts have surfaces the study's artifacts lack — wide planes at any orientation, concave pockets and grooves,
saddles, edges and fillets — and the intervals failed there first (docs/parts-generalisation.md). These surfaces
are not the test parts (``blade``, ``bowl``, ``step``, ``fillet``): they span the same surface classes
(:mod:`xmetro_ros.judge.surface_class`) with other shapes and sizes, so a calibration on them is judged on parts
it never saw.

- ``plate``: a flat plate (48 × 36 mm);
- ``groove``: a plate with a concave cylindrical groove (R 12 mm, 4 mm deep, along X) and a spherical dimple
  (R 18 mm, Ø16 mm opening);
- ``saddle``: z = (x² − y²) / (2 · 30 mm) (principal curvatures ±1/30 /mm at the centre);
- ``ridge``: a ridge along X with 35° flanks, a convex R 2 mm fillet on top and concave R 2 mm fillets at its foot.

:func:`surface_campaign` presents each under the study's settings at a cycle of tilts (planes at many
orientations), the way :mod:`xmetro_ros.parts.study` presents the test parts.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from .generated_parts import _fillet_profile, _grid, heightfield_solid
from .mesh import MeshArtifact

__all__ = ["SURFACES", "TILTS_DEG", "make_surface", "surface_campaign", "surface_presentation"]


def _plate(step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xs, ys = _grid(-24.0, 24.0, max(step, 2.0)), _grid(-18.0, 18.0, max(step, 2.0))
    return xs, ys, np.zeros((len(xs), len(ys)))


def _groove(step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xs, ys = _grid(-24.0, 24.0, step), _grid(-18.0, 18.0, step)
    x, y = np.meshgrid(xs, ys, indexing="ij")
    rg, dg, yg = 12.0, 4.0, -8.0  # groove radius, depth, axis position (along X)
    hw = np.sqrt(rg**2 - (rg - dg) ** 2)
    z = np.where(np.abs(y - yg) < hw, (rg - dg) - np.sqrt(np.maximum(rg**2 - (y - yg) ** 2, 0.0)), 0.0)
    rd, ro, xd, yd = 18.0, 8.0, 10.0, 8.0  # dimple radius, opening radius, centre
    r2 = (x - xd) ** 2 + (y - yd) ** 2
    zc = np.sqrt(rd**2 - ro**2)
    return xs, ys, np.where(r2 < ro**2, zc - np.sqrt(np.maximum(rd**2 - r2, 0.0)), z)


def _saddle(step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xs, ys = _grid(-20.0, 20.0, step), _grid(-16.0, 16.0, step)
    x, y = np.meshgrid(xs, ys, indexing="ij")
    return xs, ys, (x**2 - y**2) / (2.0 * 30.0)


def _ridge(step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xs, ys = _grid(-20.0, 20.0, step), _grid(-18.0, 18.0, step / 2)
    # the fillet profile's top half mirrored: floor, concave fillet, 35° flank, convex fillet, top, and back down
    half = _fillet_profile(np.abs(ys) - 8.0, h=6.0, r=2.0, beta_deg=35.0, y1=-6.0)
    return xs, ys, np.broadcast_to(half, (len(xs), len(ys))).copy()


#: name → surface generator (grid step mm → xs, ys, z)
SURFACES: dict[str, Callable[[float], tuple[np.ndarray, np.ndarray, np.ndarray]]] = {
    "plate": _plate, "groove": _groove, "saddle": _saddle, "ridge": _ridge,
}
#: tilts (about X, about Y) in degrees cycled over the settings: a surface is seen at many orientations
TILTS_DEG = ((0.0, 0.0), (20.0, 0.0), (0.0, -20.0), (-12.0, 12.0), (30.0, 10.0), (-25.0, -5.0))


def make_surface(name: str, step_mm: float = 0.3) -> MeshArtifact:
    """The calibration surface ``name`` (nominal: no form error) as a MeshArtifact."""
    if name not in SURFACES:
        raise KeyError(f"unknown calibration surface {name!r} (known: {', '.join(SURFACES)})")
    xs, ys, z = SURFACES[name](float(step_mm))
    v, f = heightfield_solid(xs, ys, z)
    return MeshArtifact(v, f, name=f"cal-{name}", source={"surface": name, "step_mm": float(step_mm)})


def surface_presentation(tilt_deg: tuple[float, float], turn_deg: float = -3.0) -> np.ndarray:
    """Surface → scan frame transform (4, 4): tilted about X then Y by ``tilt_deg``, turned about Z, raised 12 mm
    (within the training stand-offs) and shifted off the grid lines (0.29, 0.17) mm."""
    ax, ay = np.radians(tilt_deg)
    az = np.radians(turn_deg)
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    t = np.eye(4)
    t[:3, :3] = rz @ ry @ rx
    t[:3, 3] = (0.29, 0.17, 12.0)
    return t


def surface_campaign(scanner: Any, seed: int, stride: int = 1, surfaces: tuple[str, ...] = tuple(SURFACES)
                     ) -> list[tuple[MeshArtifact, Any, int, str]]:
    """(artifact, settings, seed, label) of every surface under every ``stride``-th study setting, each setting
    with the next tilt of TILTS_DEG (a different one per surface). Simulate with
    ``simulate_scan(artifact, settings, scanner=scanner, seed=seed)``."""
    configs = scanner.study_configurations()[::stride]
    out = []
    for s, name in enumerate(surfaces):
        base = make_surface(name)
        for c, st in enumerate(configs):
            tilt = TILTS_DEG[(c + 2 * s) % len(TILTS_DEG)]
            item_seed = int(np.random.SeedSequence([int(seed), 7, s, c]).generate_state(1)[0])
            out.append((base.transformed(surface_presentation(tilt)), st, item_seed,
                        f"surface {name} tilt {tilt[0]:g}/{tilt[1]:g} deg {st.label()}"))
    return out
