"""Test parts generated in code (deterministic numpy): CAD meshes and their manufactured versions with a known
form error. Millimetres, part frame = scan frame of the default pose (the scanner 90 mm above the origin, looking
down along −Z); every part sits within |x| ≤ 24, |y| ≤ 18, −12 ≤ z ≤ 10 mm.

- ``blade``: a cambered, twisted freeform surface (turbine-blade-like pressure side) on a block;
- ``bowl``: a plate with a spherical pocket (concave; R 25 mm, opening Ø32 mm, 5.8 mm deep; convex rim);
- ``step``: a stepped block (two vertical walls across the scan direction: sharp convex and concave edges, the
  camera occluded by the part behind the rising wall);
- ``fillet``: a block with a 50° ramp between convex and concave fillets of R 3 mm;
- ``saddle``: a block with a saddle top, z = 4 + x² / (2 · 45) − y² / (2 · 25) mm (principal curvatures −1/45
  along x and +1/25 /mm along y at the centre, convex positive: unlike the calibration saddle's ±1/30, not
  symmetric);
- ``torus``: a half torus ring lying on a plate (ring radius 11 mm, tube radius 5 mm): convex outside, saddle on
  its inner side, a concave 90° crease where the tube meets the plate, a flat centre Ø12 mm;
- ``eggcrate``: a block with an egg-crate top, z = 3 + 1.5 · cos(2πx / 20) · cos(2πy / 20) mm (convex bumps,
  concave pits, saddles between; curvatures up to ±0.15 /mm, slopes up to 25°).

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

__all__ = ["PARTS", "apply_form_error", "form_field", "heightfield_solid", "make_part", "part_geometry", "refine_edges"]

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


def _saddle(step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xs, ys = _grid(-22.0, 22.0, step), _grid(-17.0, 17.0, step)
    x, y = np.meshgrid(xs, ys, indexing="ij")
    return xs, ys, 4.0 + x**2 / (2.0 * 45.0) - y**2 / (2.0 * 25.0)


def _torus(step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ring, tube = 11.0, 5.0
    xs, ys = _grid(-21.0, 21.0, step), _grid(-18.0, 18.0, step)
    x, y = np.meshgrid(xs, ys, indexing="ij")
    d = np.hypot(x, y) - ring
    return xs, ys, np.sqrt(np.maximum(tube**2 - d**2, 0.0))


def _eggcrate(step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xs, ys = _grid(-22.0, 22.0, step), _grid(-18.0, 18.0, step)
    x, y = np.meshgrid(xs, ys, indexing="ij")
    k = 2.0 * np.pi / 20.0
    return xs, ys, 3.0 + 1.5 * np.cos(k * x) * np.cos(k * y)


#: name → surface generator (grid step mm → xs, ys, z)
PARTS: dict[str, Callable[[float], tuple[np.ndarray, np.ndarray, np.ndarray]]] = {
    "blade": _blade, "bowl": _bowl, "step": _step, "fillet": _fillet,
    "saddle": _saddle, "torus": _torus, "eggcrate": _eggcrate,
}


def form_field(points: np.ndarray, amplitude_um: float, *, center_mm: tuple[float, float] = (0.0, 0.0),
               sigma_mm: float = 6.0) -> np.ndarray:
    """The known form error (mm, along +Z) of a manufactured part at ``points`` (N, 3) mm: a bump of
    +``amplitude_um`` (Gaussian, σ 6 mm, at (8, 4)) and a dip of −0.6·amplitude (σ 5 mm, at (−9, −5)); smooth
    (slope ≤ 0.005 at 50 µm), so the scanner sees it as a change of shape, not of its own error.

    ``center_mm`` (x, y) moves the pattern (the generated parts: the origin, the centre of each); ``sigma_mm``
    scales it (positions and widths by ``sigma_mm`` / 6; the generated parts: 6)."""
    p = np.asarray(points, dtype=np.float64)
    a = amplitude_um * 1e-3
    s = float(sigma_mm) / 6.0
    cx, cy = (float(c) for c in center_mm)
    g1 = np.exp(-((p[:, 0] - (cx + 8.0 * s)) ** 2 + (p[:, 1] - (cy + 4.0 * s)) ** 2) / (2 * (6.0 * s) ** 2))
    g2 = np.exp(-((p[:, 0] - (cx - 9.0 * s)) ** 2 + (p[:, 1] - (cy - 5.0 * s)) ** 2) / (2 * (5.0 * s) ** 2))
    return a * (g1 - 0.6 * g2)


def refine_edges(vertices: np.ndarray, triangles: np.ndarray, max_edge_mm: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The same surface with no edge longer than ``max_edge_mm``: every longer edge split at its midpoint (shared
    by both its triangles: no cracks), each triangle re-cut into 2, 3 or 4 with its winding, until none is left.
    The surface is unchanged (new vertices lie on the old triangles); only where the edges are long are there
    more triangles."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(triangles, dtype=np.int64)
    if not (np.isfinite(max_edge_mm) and max_edge_mm > 0):
        raise ValueError(f"max_edge_mm must be positive, got {max_edge_mm}")
    for _ in range(200):
        nf = len(f)
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)  # edge k of face i: k*F + i
        long = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1) > max_edge_mm
        if not long.any():
            return v, f
        le, inv = np.unique(e[long], axis=0, return_inverse=True)
        mid_id = np.full(len(e), -1, dtype=np.int64)
        mid_id[long] = len(v) + inv.reshape(-1)
        v = np.vstack([v, 0.5 * (v[le[:, 0]] + v[le[:, 1]])])
        m = mid_id.reshape(3, nf).T  # (F, 3): the midpoint on edge (0, 1), (1, 2), (2, 0) or −1
        split = m >= 0
        n = split.sum(axis=1)
        # Rotate each face (cyclically: the winding stays) so that one split edge is edge 0 (one split) or the
        # unsplit edge is edge 2 (two splits).
        r = np.zeros(nf, dtype=np.int64)
        r[n == 1] = np.argmax(split[n == 1], axis=1)
        r[n == 2] = (np.argmin(split[n == 2], axis=1) + 1) % 3
        idx = (r[:, None] + np.arange(3)) % 3
        fv, fm = np.take_along_axis(f, idx, axis=1), np.take_along_axis(m, idx, axis=1)
        a, b, c = fv[:, 0], fv[:, 1], fv[:, 2]
        m0, m1, m2 = fm[:, 0], fm[:, 1], fm[:, 2]
        out = [f[n == 0]]
        k = n == 1
        out += [np.stack([a[k], m0[k], c[k]], 1), np.stack([m0[k], b[k], c[k]], 1)]
        k = n == 2
        out += [np.stack([m0[k], b[k], m1[k]], 1), np.stack([a[k], m0[k], m1[k]], 1), np.stack([a[k], m1[k], c[k]], 1)]
        k = n == 3
        out += [np.stack([a[k], m0[k], m2[k]], 1), np.stack([m0[k], b[k], m1[k]], 1),
                np.stack([m2[k], m1[k], c[k]], 1), np.stack([m0[k], m1[k], m2[k]], 1)]
        f = np.vstack(out)
    raise ValueError(f"refine_edges: edges still longer than {max_edge_mm} mm after 200 rounds")


def apply_form_error(mesh: MeshArtifact, amplitude_um: float, sigma_mm: float = 6.0,
                     center_mm: tuple[float, float] | None = None) -> MeshArtifact:
    """Any mesh (part frame, not yet posed) made into a manufactured part with the generated parts' form error
    (``form_field``): every vertex moved along the part's +Z by ``form_field`` scaled to ``amplitude_um``, with
    the pattern centred on ``center_mm`` (x, y; default the centre of the mesh's bounding box) and scaled by
    ``sigma_mm``. Edges longer than ``sigma_mm`` / 4 are split first (``refine_edges``), so the manufactured
    surface follows the field (within 1 % of its amplitude) on a CAD of large flat triangles. The truth is
    recorded in the mesh's ``source`` (``form_um``, ``form_sigma_mm``, ``form_center_mm``), which ``to_dict`` (and
    so a scan's artifact in a bag) keeps and ``scan.artifact_specs.mesh_from_dict`` rebuilds from."""
    if not np.allclose(mesh.transform, np.eye(4)):
        raise ValueError("apply_form_error: the mesh is already posed; give it in its part frame")
    if not (np.isfinite(amplitude_um) and np.isfinite(sigma_mm) and sigma_mm > 0):
        raise ValueError(f"form error: amplitude {amplitude_um} µm and σ {sigma_mm} mm must be finite, σ > 0")
    if center_mm is None:
        lo, hi = mesh.bounds()
        center_mm = (float(0.5 * (lo[0] + hi[0])), float(0.5 * (lo[1] + hi[1])))
    v, f = refine_edges(mesh.vertices, mesh.triangles, float(sigma_mm) / 4.0)
    v = v.copy()
    v[:, 2] += form_field(v, amplitude_um, center_mm=center_mm, sigma_mm=sigma_mm)
    src = None if mesh.source is None else {
        **mesh.source, "form_um": float(amplitude_um), "form_sigma_mm": float(sigma_mm),
        "form_center_mm": [float(center_mm[0]), float(center_mm[1])]}
    return MeshArtifact(v, f, name=f"{mesh.name}+form{amplitude_um:g}um", source=src, crease_deg=mesh.crease_deg)


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
