"""Triangle-mesh artifacts: any part (STL / PLY / OBJ) as the nominal surface of the virtual scanner and of the
targets. Lengths in mm, in the scan frame.

``MeshArtifact`` has the interface of :class:`xmetro_ros.scan.artifacts.Artifact`:

- ``intersect(origins, dirs)``: first hit along each ray (mm, NaN = miss). The bounding-volume hierarchy of
  open3d's ``RaycastingScene`` finds the triangle (float32); the depth is then recomputed on that triangle in
  float64, so a tessellated shape agrees with its analytic form to its chord error (sub-µm on a fine mesh). Hits
  closer than ``SELF_HIT_MM`` to the ray's origin are skipped (a ray leaving the surface does not hit its own
  triangle): the scanner's camera-occlusion test by the part itself.
- ``project(points)``: the closest point on the mesh (open3d's closest-point query, refined in float64 on the
  triangle it returns) — the projection along the surface normal, so ``errors = project(p) − p`` is the study's
  nominal − measured for any shape.
- ``normals(points)``: smooth normals of the surface at the closest point, interpolated (barycentric) from corner
  normals that average the faces around a vertex whose normals lie within ``crease_deg`` of the face's: curved
  surfaces get smooth normals, sharp edges stay sharp. Outward = the triangles' winding (counter-clockwise seen
  from outside).

open3d is imported lazily, on the first query (it is a ``[train]`` extra, not a runtime dependency: the node and
``xmetro predict`` without ``--cad`` never load it). Reading and writing binary STL and binary PLY is numpy only.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .artifacts import Artifact, ArtifactSpecError, _points
from .geometry import unit

__all__ = [
    "SELF_HIT_MM",
    "MeshArtifact",
    "closest_on_triangles",
    "read_mesh",
    "write_ply",
    "write_stl",
]

#: Hits closer than this to a ray's origin are skipped (mm): a ray cast from a surface point does not see its own
#: triangle (float32 BVH round-off is ~1e-5 mm at 100 mm).
SELF_HIT_MM = 1e-3
_MAX_RECASTS = 4


def closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (N, 3) of the point of triangle (a, b, c) closest to p, all (N, 3) float64 mm
    (Ericson, Real-Time Collision Detection, 5.1.5; vectorised)."""
    ab, ac = b - a, c - a
    ap, bp, cp = p - a, p - b, p - c

    def dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.einsum("ij,ij->i", u, v)

    d1, d2 = dot(ab, ap), dot(ac, ap)
    d3, d4 = dot(ab, bp), dot(ac, bp)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(invalid="ignore", divide="ignore"):
        s = va + vb + vc
        v_in, w_in = vb / s, vc / s
        bary = np.stack([1.0 - v_in - w_in, v_in, w_in], axis=1)
        # Regions in reverse order of precedence (the later assignment wins, as Ericson's early returns).
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        m = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
        bary[m] = np.stack([np.zeros(m.sum()), 1.0 - w[m], w[m]], axis=1)
        w = d2 / (d2 - d6)
        m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        bary[m] = np.stack([1.0 - w[m], np.zeros(m.sum()), w[m]], axis=1)
        m = (d6 >= 0) & (d5 <= d6)
        bary[m] = (0.0, 0.0, 1.0)
        v = d1 / (d1 - d3)
        m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        bary[m] = np.stack([1.0 - v[m], v[m], np.zeros(m.sum())], axis=1)
        m = (d3 >= 0) & (d4 <= d3)
        bary[m] = (0.0, 1.0, 0.0)
        m = (d1 <= 0) & (d2 <= 0)
        bary[m] = (1.0, 0.0, 0.0)
    bad = ~np.isfinite(bary).all(axis=1)  # degenerate triangle: its first vertex
    bary[bad] = (1.0, 0.0, 0.0)
    return bary


class MeshArtifact(Artifact):
    """A part given by a triangle mesh, in the scan frame (mm).

    Args:
        vertices: (V, 3) float64 mm.
        triangles: (F, 3) vertex indices, counter-clockwise seen from outside (outward normals).
        name: a label (part name or file stem).
        source: how to rebuild it (``to_dict``): {"part": name, ...} for a generated part
        (xmetro_ros.scan.generated_parts) or
            {"path": file}; None → the vertices and triangles are written into the dict (small meshes only).
        crease_deg: faces around a vertex whose normals differ by more than this are not smoothed together.
        transform: (4, 4) rigid transform already applied to ``vertices`` (part frame → scan frame), recorded for
            ``to_dict``; identity by default.
    """

    kind = "mesh"

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, *, name: str = "mesh",
                 source: dict[str, Any] | None = None, crease_deg: float = 30.0,
                 transform: np.ndarray | None = None) -> None:
        v = np.ascontiguousarray(vertices, dtype=np.float64)
        f = np.ascontiguousarray(triangles, dtype=np.int64)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise ArtifactSpecError(f"a mesh needs vertices (V, 3) and triangles (F, 3), got {v.shape}, {f.shape}")
        if not np.isfinite(v).all() or f.min() < 0 or f.max() >= len(v):
            raise ArtifactSpecError("mesh vertices must be finite and triangle indices within the vertices")
        area2 = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
        f = f[area2 > 1e-12]  # degenerate triangles carry no surface
        if len(f) == 0:
            raise ArtifactSpecError("the mesh has no triangle of non-zero area")
        self.vertices, self.triangles = v, f
        self.name, self.source, self.crease_deg = str(name), source, float(crease_deg)
        self.transform = np.eye(4) if transform is None else np.asarray(transform, dtype=np.float64)
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        cr = np.cross(b - a, c - a)
        self.face_normals = cr / np.linalg.norm(cr, axis=1, keepdims=True)
        self.face_areas = 0.5 * np.linalg.norm(cr, axis=1)
        self.center = 0.5 * (v.min(axis=0) + v.max(axis=0))  # the BVH works relative to it (float32 precision)
        self._corner_angles = _corner_angles(a, b, c)
        self._scene: Any = None
        self._corner_table: np.ndarray | None = None
        self._vf_ptr, self._vf_face = _vertex_faces(f, len(v))

    # --- construction -------------------------------------------------------------------------------------------
    @classmethod
    def from_file(cls, path: str | Path, *, crease_deg: float = 30.0) -> MeshArtifact:
        """Read a mesh file (STL, PLY, OBJ; mm)."""
        v, f = read_mesh(path)
        return cls(v, f, name=Path(path).stem, source={"path": str(Path(path).resolve())}, crease_deg=crease_deg)

    def transformed(self, transform: np.ndarray) -> MeshArtifact:
        """The same part moved by the rigid ``transform`` (4, 4) (applied after the current one)."""
        t = np.asarray(transform, dtype=np.float64)
        v = self.vertices @ t[:3, :3].T + t[:3, 3]
        return MeshArtifact(v, self.triangles, name=self.name, source=self.source, crease_deg=self.crease_deg,
                            transform=t @ self.transform)

    def to_dict(self) -> dict:
        d: dict[str, Any] = {"kind": "mesh", "name": self.name, "crease_deg": self.crease_deg,
                             "transform": self.transform.tolist()}
        if self.source is not None:
            d["source"] = dict(self.source)
        else:
            untransformed = _apply(np.linalg.inv(self.transform), self.vertices)
            d["vertices"] = untransformed.tolist()
            d["triangles"] = self.triangles.tolist()
        return d

    # --- queries ------------------------------------------------------------------------------------------------
    def scene(self) -> Any:
        """open3d ``RaycastingScene`` of the triangles (relative to ``center``), built on first use."""
        if self._scene is None:
            import open3d as o3d

            sc = o3d.t.geometry.RaycastingScene()
            sc.add_triangles(o3d.core.Tensor.from_numpy(np.ascontiguousarray(self.vertices - self.center, np.float32)),
                             o3d.core.Tensor.from_numpy(np.ascontiguousarray(self.triangles, np.uint32)))
            self._scene = sc
        return self._scene

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(depth (N,) mm, triangle index (N,), −1 = miss) of the first hit beyond ``SELF_HIT_MM`` along unit
        ``dirs`` from ``origins`` (both (N, 3) mm, scan frame)."""
        import open3d as o3d

        o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
        n = len(o)
        depth = np.full(n, np.nan)
        tri = np.full(n, -1, dtype=np.int64)
        start = np.zeros(n)  # distance already travelled by each recast
        todo = np.arange(n)
        for _ in range(_MAX_RECASTS):
            if len(todo) == 0:
                break
            oo = o[todo] + start[todo, None] * d[todo] - self.center
            rays = np.hstack([oo, d[todo]]).astype(np.float32)
            ans = self.scene().cast_rays(o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays)))
            pid = ans["primitive_ids"].numpy().astype(np.int64)
            hit = pid != int(self.scene().INVALID_ID)
            todo, pid = todo[hit], pid[hit]
            t = self._plane_depth(o[todo], d[todo], pid)
            ok = np.isfinite(t) & (t > start[todo] + SELF_HIT_MM)
            depth[todo[ok]], tri[todo[ok]] = t[ok], pid[ok]
            # Self hit (or a hit the float32 BVH placed before the skip distance): cast again from past it.
            again = todo[~ok]
            start[again] = np.maximum(start[again], np.nan_to_num(t[~ok], nan=0.0)) + SELF_HIT_MM
            todo = again
        return depth, tri

    def _plane_depth(self, o: np.ndarray, d: np.ndarray, tri: np.ndarray) -> np.ndarray:
        """Exact (float64) depth along d from o to the plane of triangle ``tri`` (NaN when parallel)."""
        n = self.face_normals[tri]
        a = self.vertices[self.triangles[tri, 0]]
        den = np.einsum("ij,ij->i", d, n)
        with np.errstate(invalid="ignore", divide="ignore"):
            t = np.einsum("ij,ij->i", a - o, n) / den
        t[np.abs(den) < 1e-12] = np.nan
        return t

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Distance along unit ``dirs`` from ``origins`` to the first hit (NaN where the ray misses), mm."""
        return self.cast(origins, dirs)[0]

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(closest points (N, 3) mm, their triangle (N,), barycentric coordinates (N, 3)) on the mesh."""
        import open3d as o3d

        p = _points(points)
        if len(p) == 0:
            return np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros((0, 3))
        ans = self.scene().compute_closest_points(
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(p - self.center, np.float32)))
        tri = ans["primitive_ids"].numpy().astype(np.int64)
        q, bary = self._on_triangles(p, tri)
        # float32 may pick a neighbour of the closest triangle; then the float64 closest point lies on that
        # triangle's boundary: those rows take the closest among the faces around its vertices.
        edge = np.flatnonzero(bary.min(axis=1) <= 1e-9)
        if len(edge):
            verts = self.triangles[tri[edge]].reshape(-1)
            lo, hi = self._vf_ptr[verts], self._vf_ptr[verts + 1]
            cnt = hi - lo
            row = np.repeat(np.arange(len(verts)) // 3, cnt)
            cand = self._vf_face[np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt) + np.repeat(lo, cnt)]
            pr = p[edge][row]
            qc, bc = self._on_triangles(pr, cand)
            d2 = np.einsum("ij,ij->i", qc - pr, qc - pr)
            best = np.lexsort((d2, row))  # by row, then distance: the first of each row is its closest
            first = best[np.r_[0, np.flatnonzero(np.diff(row[best])) + 1]]
            q[edge], tri[edge], bary[edge] = qc[first], cand[first], bc[first]
        return q, tri, bary

    def _on_triangles(self, p: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(closest points (N, 3), barycentric coordinates (N, 3)) of p (N, 3) on triangles ``tri`` (N,)."""
        f = self.triangles[tri]
        a, b, c = self.vertices[f[:, 0]], self.vertices[f[:, 1]], self.vertices[f[:, 2]]
        bary = closest_on_triangles(p, a, b, c)
        return bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c, bary

    def project(self, points: np.ndarray) -> np.ndarray:
        return self.closest(points)[0]

    def normals(self, points: np.ndarray) -> np.ndarray:
        """Outward unit normals (N, 3) at the surface point closest to each of ``points``."""
        _, tri, bary = self.closest(points)
        return self.normals_on(tri, bary)

    def normals_on(self, tri: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Smooth (crease-aware) normals at barycentric ``bary`` (N, 3) of triangles ``tri`` (N,)."""
        if self._corner_table is None:  # all corners once (a fan vertex of valence k costs k² otherwise, per query)
            f = len(self.triangles)
            step = max(1, 100_000 // 3)
            self._corner_table = np.concatenate(
                [self.corner_normals(np.arange(i, min(i + step, f))) for i in range(0, f, step)])
        cn = self._corner_table[np.asarray(tri, dtype=np.int64)]  # (N, 3 corners, 3)
        return unit(np.einsum("nk,nkj->nj", bary, cn))

    def corner_normals(self, tri: np.ndarray) -> np.ndarray:
        """(N, 3, 3) normals at the three corners of triangles ``tri``: angle-weighted mean of the normals of the
        faces around the corner's vertex within ``crease_deg`` of the triangle's own normal."""
        tri = np.asarray(tri, dtype=np.int64)
        verts = self.triangles[tri].reshape(-1)  # (3N,)
        own = np.repeat(self.face_normals[tri], 3, axis=0)  # (3N, 3)
        lo, hi = self._vf_ptr[verts], self._vf_ptr[verts + 1]
        cnt = hi - lo
        row = np.repeat(np.arange(len(verts)), cnt)
        pos = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt) + np.repeat(lo, cnt)
        face = self._vf_face[pos]  # (K,) a face around the vertex of corner `row`
        fn = self.face_normals[face]
        keep = np.einsum("ij,ij->i", fn, own[row]) >= np.cos(np.radians(self.crease_deg))
        # weight: the face's angle at that vertex
        corner_of = np.argmax(self.triangles[face] == verts[row][:, None], axis=1)
        wgt = self._corner_angles[face, corner_of] * keep
        acc = np.zeros((len(verts), 3))
        for k in range(3):
            acc[:, k] = np.bincount(row, weights=wgt * fn[:, k], minlength=len(verts))
        return unit(np.where(np.linalg.norm(acc, axis=1, keepdims=True) > 0, acc, own)).reshape(-1, 3, 3)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box (lo (3,), hi (3,)) of the vertices, mm, scan frame."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    def sample(self, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """``n`` points drawn uniformly over the surface (area-weighted), with their smooth normals."""
        rng = np.random.default_rng(seed)
        tri = rng.choice(len(self.triangles), size=int(n), p=self.face_areas / self.face_areas.sum())
        r1, r2 = rng.random(n), rng.random(n)
        s = np.sqrt(r1)
        bary = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
        f = self.triangles[tri]
        p = np.einsum("nk,nkj->nj", bary, self.vertices[f])
        return p, self.normals_on(tri, bary)

    def __repr__(self) -> str:
        return f"MeshArtifact({self.name!r}, {len(self.vertices)} vertices, {len(self.triangles)} triangles)"


def _apply(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ t[:3, :3].T + t[:3, 3]


def _corner_angles(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(F, 3) interior angles (rad) at corners a, b, c."""

    def ang(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        cos = np.einsum("ij,ij->i", u, v) / (np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1))
        return np.arccos(np.clip(cos, -1.0, 1.0))

    return np.stack([ang(b - a, c - a), ang(a - b, c - b), ang(a - c, b - c)], axis=1)


def _vertex_faces(f: np.ndarray, nv: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR adjacency vertex → faces: (pointer (V+1,), face indices)."""
    verts = f.reshape(-1)
    faces = np.repeat(np.arange(len(f)), 3)
    order = np.argsort(verts, kind="stable")
    ptr = np.zeros(nv + 1, dtype=np.int64)
    ptr[1:] = np.cumsum(np.bincount(verts, minlength=nv))
    return ptr, faces[order]


# --- files ---------------------------------------------------------------------------------------------------------
_STL_DTYPE = np.dtype([("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")])


def write_stl(path: str | Path, vertices: np.ndarray, triangles: np.ndarray, header: str = "xmetro_ros part") -> Path:
    """Binary STL (float32, mm) of the mesh."""
    v, f = np.asarray(vertices, np.float64), np.asarray(triangles, np.int64)
    rec = np.zeros(len(f), dtype=_STL_DTYPE)
    tri = v[f]
    cr = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    rec["n"] = cr / np.maximum(np.linalg.norm(cr, axis=1, keepdims=True), 1e-300)
    rec["v"] = tri
    path = Path(path)
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii", "replace")[:80].ljust(80, b" "))
        fh.write(np.uint32(len(f)).tobytes())
        fh.write(rec.tobytes())
    return path


def write_ply(path: str | Path, vertices: np.ndarray, triangles: np.ndarray) -> Path:
    """Binary little-endian PLY with float64 vertices (mm) and int32 triangles."""
    v, f = np.asarray(vertices, "<f8"), np.asarray(triangles, np.int64)
    head = ("ply\nformat binary_little_endian 1.0\ncomment xmetro_ros part, mm\n"
            f"element vertex {len(v)}\nproperty double x\nproperty double y\nproperty double z\n"
            f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n")
    faces = np.zeros(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"], faces["i"] = 3, f
    path = Path(path)
    with open(path, "wb") as fh:
        fh.write(head.encode("ascii"))
        fh.write(np.ascontiguousarray(v).tobytes())
        fh.write(faces.tobytes())
    return path


def _read_binary_stl(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    n = int(np.frombuffer(data, "<u4", count=1, offset=80)[0])
    rec = np.frombuffer(data, dtype=_STL_DTYPE, count=n, offset=84)
    corners = rec["v"].reshape(-1, 3).astype(np.float64)
    verts, inv = np.unique(corners, axis=0, return_inverse=True)
    return verts, inv.reshape(-1, 3)


def read_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64 mm, triangles (F, 3)) of an STL, PLY or OBJ file. Binary STL is read with numpy
    (coincident corners merged); ASCII STL, PLY and OBJ with open3d (``[train]`` extra)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file {path} not found")
    suffix = path.suffix.lower()
    if suffix not in (".stl", ".ply", ".obj"):
        raise ArtifactSpecError(f"unknown mesh format {suffix!r} of {path} (STL, PLY or OBJ)")
    data = path.read_bytes()
    if suffix == ".stl" and len(data) >= 84 and len(data) == 84 + 50 * int.from_bytes(data[80:84], "little"):
        return _read_binary_stl(data)
    import open3d as o3d

    m = o3d.io.read_triangle_mesh(path)
    v, f = np.asarray(m.vertices, np.float64), np.asarray(m.triangles, np.int64)
    if len(f) == 0:
        raise ArtifactSpecError(f"{path} holds no triangles")
    return v, f
