"""Test parts generated in code (deterministic numpy): CAD meshes and their manufactured versions with a known
form error. Millimetres, part frame = scan frame of the default pose (the scanner 90 mm above the origin, looking
down along −Z); every part sits within |x| ≤ 24, |y| ≤ 18, −12 ≤ z ≤ 10 mm.

- ``blade``: a cambered, twisted freeform surface (turbine-blade-like pressure side) on a block;
- ``bowl``: a plate with a spherical pocket (concave; R 25 mm, opening Ø32 mm, 5.8 mm deep; convex rim);
- ``step``: a stepped block (two vertical walls across the scan direction: sharp convex and concave edges, the
  camera occluded by the part behind the rising wall);
- ``fillet``: a block with a 50° ramp between convex and concave fillets of R 3 mm.

Each part is a closed height-field solid: the top surface z = g(x, y) on a grid (duplicate grid lines make vertical
walls), four side walls and a bottom. ``make_part(name, form_um)``: the CAD (``form_um`` 0) or the manufactured
part whose every vertex is moved along +Z by the known smooth form error ``form_field`` scaled to ``form_um``
(coincident vertices move together: no cracks). ``xmetro parts DIR`` writes them as STL / PLY.
"""

from __future__ import annotations

from collections.abc import Callable
from itertools import pairwise

import numpy as np

from .mesh import MeshArtifact

__all__ = ["PARTS", "form_field", "heightfield_solid", "make_part", "part_geometry"]

_BASE_Z = -12.0  # bottom of every part (mm)


def heightfield_solid(xs: np.ndarray, ys: np.ndarray, z: np.ndarray, base_z: float = _BASE_Z
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Closed solid under the surface z[i, j] = g(xs[i], ys[j]) down to ``base_z`` (mm): (vertices, triangles),
    outward winding. ``xs`` / ``ys`` ascending; a repeated value makes a vertical wall."""
    nx, ny = len(xs), len(ys)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    top = np.stack([gx, gy, z], axis=-1).reshape(-1, 3)
    idx = np.arange(nx * ny).reshape(nx, ny)
    v00, v10, v11, v01 = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    tris: list[np.ndarray] = [np.stack([v00, v10, v11], -1).reshape(-1, 3),
                              np.stack([v00, v11, v01], -1).reshape(-1, 3)]
    # Boundary loop of the top grid, counter-clockwise seen from above.
    ring = np.concatenate([idx[:, 0], idx[-1, 1:], idx[-2::-1, -1], idx[0, -2:0:-1]])
    bottom = top[ring].copy()
    bottom[:, 2] = base_z
    nb = len(top)
    bidx = nb + np.arange(len(ring))
    a, b = ring, np.roll(ring, -1)
    ab, bb = bidx, np.roll(bidx, -1)
    # Wall quad (a, b, bb, ab): outward for a counter-clockwise ring.
    tris += [np.stack([a, ab, bb], -1), np.stack([a, bb, b], -1)]
    centre = len(top) + len(ring)
    tris.append(np.stack([np.full(len(ring), centre), bb, ab], -1))  # bottom fan, facing −Z
    c = np.array([[0.5 * (xs[0] + xs[-1]), 0.5 * (ys[0] + ys[-1]), base_z]])
    return np.vstack([top, bottom, c]), np.vstack(tris).astype(np.int64)


def _grid(lo: float, hi: float, step: float, walls: tuple[float, ...] = ()) -> np.ndarray:
    """Ascending grid lo..hi with spacing ≤ step, each value of ``walls`` present twice (a vertical wall)."""
    knots = np.unique(np.concatenate([[lo, hi], walls]))
    pieces = [np.linspace(a, b, max(int(np.ceil((b - a) / step)), 1) + 1)[:-1] for a, b in pairwise(knots)]
    g = np.concatenate([*pieces, [hi]])
    return np.sort(np.concatenate([g, np.asarray(walls, dtype=float)]))


def _blade(step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xs, ys = _grid(-24.0, 24.0, step), _grid(-16.0, 16.0, step)
    x, y = np.meshgrid(xs, ys, indexing="ij")
    camber = 7.0 * (1.0 - (x / 27.0) ** 2) * (1.0 + 0.25 * y / 16.0)
    twist = np.tan(np.radians(12.0) * y / 16.0) * x * 0.5
    return xs, ys, camber + twist + 0.6 * np.sin(x / 7.0) * np.cos(y / 9.0)


def _bowl(step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rb, ro = 25.0, 16.0
    xs, ys = _grid(-22.0, 22.0, step), _grid(-18.0, 18.0, step)
    x, y = np.meshgrid(xs, ys, indexing="ij")
    r2 = x**2 + y**2
    zc = np.sqrt(rb**2 - ro**2)
    z = np.where(r2 < ro**2, zc - np.sqrt(np.maximum(rb**2 - r2, 0.0)), 0.0)
    return xs, ys, z


def _step(step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    walls = (-5.0, 6.0)
    xs, ys = _grid(-20.0, 20.0, step), _grid(-17.0, 17.0, step, walls)
    z1 = np.where(ys < -5.0, 0.0, np.where(ys < 6.0, 7.0, 2.0))
    # the second copy of each wall line takes the level beyond the wall
    for w in walls:
        k = np.flatnonzero(ys == w)
        z1[k[0]] = 0.0 if w == -5.0 else 7.0
        z1[k[1]] = 7.0 if w == -5.0 else 2.0
    return xs, ys, np.broadcast_to(z1, (len(xs), len(ys))).copy()


def _fillet_profile(y: np.ndarray, h: float = 9.0, r: float = 3.0, beta_deg: float = 50.0, y1: float = -6.0
                    ) -> np.ndarray:
    """z(y) of a top at h, a convex fillet (R r) into a ramp at beta, a concave fillet (R r) into the floor z 0."""
    b = np.radians(beta_deg)
    p1y, p1z = y1 + r * np.sin(b), h - r + r * np.cos(b)
    dz = p1z - (r - r * np.cos(b))
    y2 = p1y + dz / np.tan(b) + r * np.sin(b)
    z = np.zeros_like(y)
    z[y <= y1] = h
    m = (y > y1) & (y <= p1y)
    z[m] = h - r + np.sqrt(r**2 - (y[m] - y1) ** 2)
    m = (y > p1y) & (y <= y2 - r * np.sin(b))
    z[m] = p1z - (y[m] - p1y) * np.tan(b)
    m = (y > y2 - r * np.sin(b)) & (y < y2)
    z[m] = r - np.sqrt(r**2 - (y[m] - y2) ** 2)
    return z


def _fillet(step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xs, ys = _grid(-18.0, 18.0, step), _grid(-16.0, 16.0, step / 2)
    return xs, ys, np.broadcast_to(_fillet_profile(ys), (len(xs), len(ys))).copy()


#: name → surface generator (grid step mm → xs, ys, z)
PARTS: dict[str, Callable[[float], tuple[np.ndarray, np.ndarray, np.ndarray]]] = {
    "blade": _blade, "bowl": _bowl, "step": _step, "fillet": _fillet,
}


def form_field(points: np.ndarray, amplitude_um: float) -> np.ndarray:
    """The known form error (mm, along +Z) of a manufactured part at ``points`` (N, 3) mm: a bump of
    +``amplitude_um`` (Gaussian, σ 6 mm, at (8, 4)) and a dip of −0.6·amplitude (σ 5 mm, at (−9, −5)); smooth
    (slope ≤ 0.005 at 50 µm), so the scanner sees it as a change of shape, not of its own error."""
    p = np.asarray(points, dtype=np.float64)
    a = amplitude_um * 1e-3
    g1 = np.exp(-((p[:, 0] - 8.0) ** 2 + (p[:, 1] - 4.0) ** 2) / (2 * 6.0**2))
    g2 = np.exp(-((p[:, 0] + 9.0) ** 2 + (p[:, 1] + 5.0) ** 2) / (2 * 5.0**2))
    return a * (g1 - 0.6 * g2)


def part_geometry(name: str, step_mm: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, triangles) of the CAD of part ``name`` with grid ``step_mm``."""
    if name not in PARTS:
        raise KeyError(f"unknown part {name!r} (known: {', '.join(PARTS)})")
    xs, ys, z = PARTS[name](float(step_mm))
    return heightfield_solid(xs, ys, z)


def make_part(part: str, form_um: float = 0.0, step_mm: float = 0.3) -> MeshArtifact:
    """The CAD (``form_um`` 0) or manufactured part ``part`` as a MeshArtifact (see the module docstring)."""
    v, f = part_geometry(part, step_mm)
    if form_um:
        v = v.copy()
        v[:, 2] += form_field(v, form_um)
    src = {"part": part, "form_um": float(form_um), "step_mm": float(step_mm)}
    return MeshArtifact(v, f, name=part if not form_um else f"{part}+form{form_um:g}um", source=src)
