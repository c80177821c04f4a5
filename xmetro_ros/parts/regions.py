"""Region type of points on a CAD mesh: flat, curved (convex), edge (a sharp convex crease nearby), concave (a
concave crease nearby, or concave curvature), saddle (curved both ways, in opposite senses). Millimetres, the
mesh's frame.

From surface samples of the CAD within ``radius_mm`` of the point's closest CAD point q (the face centroids plus
area-uniform samples ``spacing_mm`` apart, each with its face's normal; scipy k-d tree, the ``k`` nearest):

- a crease: a neighbour face whose normal turns more than ``crease_deg`` from the normal at q; convex when
  (n_j − n_q)·(c_j − q) > 0 (the normals spread apart, as on the outside of a box edge), concave otherwise;
- mean normal curvature κ ≈ mean over the other neighbours of k_j = (n_j − n_q)·(c_j − q) / |c_j − q|² (1/mm; > 0
  convex, < 0 concave; a sphere of radius R gives 1/R, a cylinder 1/(2R));
- principal curvatures κmin ≤ κmax: Euler's k(θ) = κ1 cos²θ + κ2 sin²θ fitted to the k_j by least squares over
  the directions θ_j of (c_j − q) in the tangent plane (the 2 × 2 second fundamental form; its eigenvalues).

Label (first that applies): ``edge`` (convex crease), ``concave`` (concave crease), ``saddle`` (κmax >
``saddle_curvature`` and κmin < −``saddle_curvature``: a saddle's H can be ~0, so the mean curvature alone calls it
flat), ``concave`` (κ < −``flat_curvature``), ``curved`` (κ > ``flat_curvature``), ``flat``. Vectorised (fixed k,
no per-point loop).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ..scan.mesh import MeshArtifact

__all__ = ["REGIONS", "label_regions"]

#: Region names; ``label_regions`` returns indices into this tuple (``saddle`` last: the older four keep their
#: indices in results files written before it).
REGIONS = ("flat", "curved", "edge", "concave", "saddle")


def label_regions(cad: MeshArtifact, points: np.ndarray, *, radius_mm: float = 1.0, crease_deg: float = 25.0,
                  flat_curvature: float = 0.004, saddle_curvature: float = 0.01, k: int = 64,
                  spacing_mm: float = 0.25, chunk: int = 20_000) -> tuple[np.ndarray, np.ndarray]:
    """(region index (N,) into :data:`REGIONS`, mean curvature (N,) 1/mm) of ``points`` (N, 3) mm, by the CAD
    surface around their closest point (see the module docstring)."""
    from scipy.spatial import cKDTree

    p = np.asarray(points, dtype=np.float64)
    if len(p) == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    q, tri, bary = cad.closest(p)
    nq = cad.normals_on(tri, bary)
    cent, cn = _surface_samples(cad, spacing_mm)
    tree = cKDTree(cent)
    kk = min(int(k), len(cent))
    lab = np.zeros(len(p), np.int64)
    curv = np.zeros(len(p))
    cos_crease = np.cos(np.radians(crease_deg))
    for s in range(0, len(p), chunk):
        sl = slice(s, s + chunk)
        dist, nb = tree.query(q[sl], k=kk, distance_upper_bound=radius_mm)
        valid = np.isfinite(dist)
        nb = np.where(valid, nb, 0)
        nj = cn[nb]  # (n, k, 3)
        dc = cent[nb] - q[sl, None, :]
        cos = np.einsum("nkj,nj->nk", nj, nq[sl])
        spread = np.einsum("nkj,nkj->nk", nj - nq[sl, None, :], dc)
        sharp = valid & (cos < cos_crease)
        convex_crease = (sharp & (spread > 0)).any(axis=1)
        concave_crease = (sharp & (spread < 0)).any(axis=1)
        d2 = np.einsum("nkj,nkj->nk", dc, dc)
        smooth = valid & ~sharp & (d2 > 1e-8)
        kap = np.where(smooth, spread / np.where(d2 > 1e-8, d2, 1.0), 0.0)
        c = kap.sum(axis=1) / np.maximum(smooth.sum(axis=1), 1)
        kmin, kmax = _principal(kap, smooth, dc, nq[sl])
        lb = np.zeros(len(c), np.int64)
        lb[c > flat_curvature] = REGIONS.index("curved")
        lb[c < -flat_curvature] = REGIONS.index("concave")
        lb[(kmax > saddle_curvature) & (kmin < -saddle_curvature)] = REGIONS.index("saddle")
        lb[concave_crease] = REGIONS.index("concave")
        lb[convex_crease] = REGIONS.index("edge")
        lab[sl], curv[sl] = lb, c
    return lab, curv


def _principal(kap: np.ndarray, w: np.ndarray, dc: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(κmin, κmax) (n,) 1/mm: the 2 × 2 form [[a, b], [b, c]] whose k(t) = a tx² + 2b tx ty + c ty² fits the
    normal curvatures ``kap`` (n, k) of the neighbours ``w`` (n, k) along their tangent directions (``dc`` (n, k, 3)
    projected on the plane of ``n`` (n, 3)); its eigenvalues. Points with too few directions get 0, 0."""
    helper = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    e1 = np.cross(n, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(n, e1)
    tx, ty = np.einsum("nkj,nj->nk", dc, e1), np.einsum("nkj,nj->nk", dc, e2)
    r = np.hypot(tx, ty)
    ok = w & (r > 1e-9)
    tx, ty = np.where(ok, tx / np.where(ok, r, 1.0), 0.0), np.where(ok, ty / np.where(ok, r, 1.0), 0.0)
    rows = np.stack([tx * tx, 2.0 * tx * ty, ty * ty], axis=-1)  # (n, k, 3); zero rows for unused neighbours
    a = np.einsum("nki,nkj->nij", rows, rows) + 1e-9 * np.eye(3)
    rhs = np.einsum("nki,nk->ni", rows, np.where(ok, kap, 0.0))
    fit = np.linalg.solve(a, rhs[..., None])[..., 0]
    well = np.linalg.cond(a) < 1e6
    # eigenvalues of [[a, b], [b, c]]: H ∓ √(((a − c)/2)² + b²), as preprocess.curvature's grid fit
    hm, dm = 0.5 * (fit[:, 0] + fit[:, 2]), np.hypot(0.5 * (fit[:, 0] - fit[:, 2]), fit[:, 1])
    return np.where(well, hm - dm, 0.0), np.where(well, hm + dm, 0.0)


def _surface_samples(cad: MeshArtifact, spacing_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(points, face normals) of the face centroids and about area / spacing² area-uniform samples (seeded)."""
    tri = cad.triangles
    cent = cad.vertices[tri].mean(axis=1)
    n = int(cad.face_areas.sum() / spacing_mm**2)
    rng = np.random.default_rng(0)
    f = rng.choice(len(tri), size=n, p=cad.face_areas / cad.face_areas.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    bary = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    pts = np.einsum("nk,nkj->nj", bary, cad.vertices[tri[f]])
    return np.vstack([cent, pts]), np.vstack([cad.face_normals, cad.face_normals[f]])
