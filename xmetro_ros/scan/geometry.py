"""Scanner-head geometry: poses, and the per-point laser / camera directions the features are built from.

Frames (see docs/conventions.md):
- World (``frame_id`` of the scan, REP 103 axes): the artifact's frame; lengths in millimetres inside the package.
- Head: the laser line (fan) runs along head +X, the head scans along head +Y, the laser points along head -Z.
  The laser source sits at the head origin; the camera sits at ``camera_mm`` in the head frame (the study's
  scanner: ``(0, baseline, 0)``, at the laser's height on +Y; another scanner's camera may sit on -Y, above or
  below the source, or off the line's centre) and looks back at the laser plane (triangulation). While scanning,
  the head translates along its own +Y axis, so the source that lit a point lies on the head's Y axis at that
  point's head-Y coordinate, and the camera moves with it.

The study's set-up is the identity orientation with the head ~90 mm above the artifact centre: then
``R_y = 90 - Z`` is ``standoff`` below.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "HeadPose",
    "PointGeometry",
    "RowPoses",
    "camera_vector",
    "matrix_to_quat",
    "orientation_grid",
    "point_geometry",
    "point_geometry_posed",
    "quat_to_matrix",
    "rotation_xyz",
    "unit",
    "vec3",
    "xyz_angles",
]


def vec3(v: Any) -> tuple[float, float, float]:
    """Three numbers (a sequence or array of 3) as a plain float triple. Raises ValueError on another length."""
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.shape != (3,):
        raise ValueError(f"expected three numbers, got {a.shape[0]}")
    return float(a[0]), float(a[1]), float(a[2])


def unit(v: np.ndarray, axis: int = -1) -> np.ndarray:
    """Normalise vectors along ``axis``; zero vectors stay zero (no NaN)."""
    n = np.linalg.norm(v, axis=axis, keepdims=True)
    return np.divide(v, n, out=np.zeros_like(v, dtype=np.result_type(v, np.float32)), where=n > 0)


def quat_to_matrix(q: np.ndarray | list[float]) -> np.ndarray:
    """Rotation matrix (3x3) from a quaternion ``(x, y, z, w)`` (ROS order). Raises ValueError on a zero quaternion."""
    x, y, z, w = (float(c) for c in q)
    n = x * x + y * y + z * z + w * w
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError(f"quaternion {tuple(q)} is zero or not finite")
    s = 2.0 / n
    return np.array(
        [
            [1 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)],
            [s * (x * y + z * w), 1 - s * (x * x + z * z), s * (y * z - x * w)],
            [s * (x * z - y * w), s * (y * z + x * w), 1 - s * (x * x + y * y)],
        ]
    )


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Quaternion ``(x, y, z, w)`` with w >= 0 from a rotation matrix."""
    r = np.asarray(r, dtype=float)
    tr = np.trace(r)
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        q = [0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif r[1, 1] > r[2, 2]:
        s = np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        q = [(r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        s = np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s, (r[1, 0] - r[0, 1]) / s]
    qa = np.asarray(q, dtype=float)
    qa /= np.linalg.norm(qa)
    return -qa if qa[3] < 0 else qa


@dataclass(frozen=True)
class HeadPose:
    """Pose of the scanner head at scan start in the scan's frame.

    Attributes:
        position: head origin (the laser source at t = 0), mm, shape (3,).
        rotation: 3x3 matrix whose columns are the head X, Y, Z axes expressed in the scan frame.
    """

    position: np.ndarray
    rotation: np.ndarray

    def __post_init__(self) -> None:
        p = np.asarray(self.position, dtype=float).reshape(3)
        r = np.asarray(self.rotation, dtype=float).reshape(3, 3)
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(r))):
            raise ValueError("head pose must be finite")
        if not np.allclose(r.T @ r, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
            raise ValueError("head rotation must be a proper rotation matrix")
        object.__setattr__(self, "position", p)
        object.__setattr__(self, "rotation", r)

    @classmethod
    def looking_down(cls, standoff_mm: float = 90.0, y_mm: float = 0.0, x_mm: float = 0.0) -> HeadPose:
        """The study's set-up: head axes = world axes, laser ``standoff_mm`` above the origin, pointing down."""
        return cls(np.array([x_mm, y_mm, standoff_mm]), np.eye(3))

    @classmethod
    def from_quaternion(cls, position: np.ndarray | list[float], q: np.ndarray | list[float]) -> HeadPose:
        """From a position (mm) and a quaternion ``(x, y, z, w)``."""
        return cls(np.asarray(position, dtype=float), quat_to_matrix(q))

    @property
    def quaternion(self) -> np.ndarray:
        """Orientation as ``(x, y, z, w)``."""
        return matrix_to_quat(self.rotation)

    def to_head(self, points: np.ndarray) -> np.ndarray:
        """Points (…, 3) in the scan frame → head frame (mm)."""
        return (np.asarray(points) - self.position) @ self.rotation

    def to_world(self, points: np.ndarray) -> np.ndarray:
        """Points (…, 3) in the head frame → scan frame (mm)."""
        return np.asarray(points) @ self.rotation.T + self.position

    def rotated(self, r_head: np.ndarray, pivot: np.ndarray | None = None) -> HeadPose:
        """The pose turned by ``r_head`` (a rotation expressed in the head frame) about ``pivot`` (scan frame, mm;
        default: the head origin). Used by the rescan recommendation to tilt / turn the head about a region."""
        r_new = self.rotation @ np.asarray(r_head, dtype=float)
        if pivot is None:
            return HeadPose(self.position, r_new)
        pivot = np.asarray(pivot, dtype=float)
        # Rotate the head origin about the pivot by the same world rotation.
        r_world = r_new @ self.rotation.T
        return HeadPose(pivot + r_world @ (self.position - pivot), r_new)


@dataclass
class PointGeometry:
    """Per-point geometry of a scan, all in the scan frame.

    Attributes:
        L: unit vectors from each point toward the laser source that lit it, (N, 3).
        V: unit vectors from each point toward the camera, (N, 3).
        source_distance: distance point → laser source, mm, (N,).
        standoff: distance from the source along the laser axis (head -Z), mm, (N,); the study's R_y = 90 - Z.
        u: position along the laser line (head X), mm, (N,).
        s: position along the scan direction (head Y), mm, (N,).
    """

    L: np.ndarray
    V: np.ndarray
    source_distance: np.ndarray
    standoff: np.ndarray
    u: np.ndarray
    s: np.ndarray


def camera_vector(camera: float | Any) -> tuple[float, float, float]:
    """The camera position in the head frame (mm): a number is a baseline along head +Y (the study's set-up)."""
    if np.ndim(camera) == 0:
        return 0.0, float(camera), 0.0
    return vec3(camera)


def point_geometry(points: np.ndarray, pose: HeadPose, camera_mm: float | Any,
                   dtype: type = np.float64) -> PointGeometry:
    """Laser and camera directions for each point of a scan taken from ``pose``.

    Args:
        points: (N, 3) points in the scan frame, mm. Must be finite.
        pose: head pose at scan start.
        camera_mm: camera position relative to the laser source in the head frame, mm (3 numbers), or a number:
            the baseline along head +Y (camera at the laser's height, the study's set-up).
        dtype: float type of the outputs (float32 on the live hot path); from a turned pose they are float64 (the
            float64 rotation's products).

    One compiled pass split over the calling thread's budget (``geometry_kernels``), in the float operations and
    types of the numpy expressions before it: head coordinates p_h = R^T (p − position) (the offsets cast to
    ``dtype``), the source on the point's head-Y line, the camera at ``camera_mm`` from it (moving with the source).
    """
    from .geometry_kernels import single_pose_geometry_rotated, single_pose_geometry_straight

    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    pts = np.ascontiguousarray(pts) if pts.dtype in (np.float32, np.float64) else pts.astype(np.float64)
    n = len(pts)
    r = np.ascontiguousarray(pose.rotation, dtype=np.float64)
    position = np.ascontiguousarray(pose.position, dtype=np.float64)
    identity = bool(np.array_equal(r, np.eye(3)))
    dt = np.dtype(dtype) if identity else np.dtype(np.float64)
    g = PointGeometry(L=np.empty((n, 3), dt), V=np.empty((n, 3), dt), source_distance=np.empty(n, dt),
                      standoff=np.empty(n, dt), u=np.empty(n, dt), s=np.empty(n, dt))
    cx, cy, cz = (float(c) for c in camera_vector(camera_mm))
    common = cx == 0.0 and cz == 0.0
    if identity:
        t = dt.type
        single_pose_geometry_straight(pts, position, t(1.0), t(0.0), t(cx), t(cy), t(cz), t(cy * cy), common,
                                      g.L, g.V, g.source_distance, g.standoff, g.u, g.s)
    else:
        single_pose_geometry_rotated(pts, position, r, np.dtype(dtype) == np.float32, cx, cy, cz, common, g.L, g.V,
                                     g.source_distance, g.standoff, g.u, g.s)
    return g


@dataclass(frozen=True)
class RowPoses:
    """The head pose each point was measured from, for a scan whose head moved or turned along the pass in any way
    (profiles assembled from a stream, each posed by /tf), instead of one pose translated along its own +Y.

    Attributes:
        positions: (P, 3) head origins (the laser source), mm, scan frame; one per profile.
        rotations: (P, 3, 3) head orientations (columns = head X, Y, Z in the scan frame), proper rotations.
        rows: int32 pose index of each point, the shape of the scan's points without the last axis ((H, W) for an
            organized scan whose row i was taken from pose i).
    """

    positions: np.ndarray
    rotations: np.ndarray
    rows: np.ndarray

    def __post_init__(self) -> None:
        p = np.asarray(self.positions, dtype=np.float64)
        r = np.asarray(self.rotations, dtype=np.float64)
        rows = np.asarray(self.rows, dtype=np.int32)
        if p.ndim != 2 or p.shape[1] != 3 or r.shape != (len(p), 3, 3) or len(p) == 0:
            raise ValueError(f"row poses need positions (P, 3) and rotations (P, 3, 3), P >= 1; got {p.shape} and "
                             f"{r.shape}")
        if not (np.isfinite(p).all() and np.isfinite(r).all()):
            raise ValueError("row poses must be finite")
        ortho = np.abs(np.einsum("pki,pkj->pij", r, r) - np.eye(3)).max(axis=(1, 2))
        if (ortho > 1e-6).any() or (np.linalg.det(r) < 0).any():
            i = int(np.flatnonzero((ortho > 1e-6) | (np.linalg.det(r) < 0))[0])
            raise ValueError(f"row pose {i}: the rotation is not a proper rotation matrix")
        if rows.size and (rows.min() < 0 or rows.max() >= len(p)):
            raise ValueError(f"row pose indices must lie in [0, {len(p)})")
        object.__setattr__(self, "positions", p)
        object.__setattr__(self, "rotations", r)
        object.__setattr__(self, "rows", rows)

    @classmethod
    def per_row(cls, positions: np.ndarray, rotations: np.ndarray, width: int) -> RowPoses:
        """Poses of an organized (H, ``width``) scan whose row i was taken from pose i."""
        h = int(np.shape(positions)[0])
        rows = np.repeat(np.arange(h, dtype=np.int32), int(width)).reshape(h, int(width))
        return cls(np.asarray(positions), np.asarray(rotations), rows)

    def __len__(self) -> int:
        return int(self.positions.shape[0])

    def first(self) -> HeadPose:
        """The pose of the first profile (the scan's ``pose``: its start)."""
        return HeadPose(self.positions[0], self.rotations[0])

    def take(self, flat_index: np.ndarray) -> RowPoses:
        """The same poses for the points ``flat_index`` of the scan (a decimated, unorganized copy)."""
        return RowPoses(self.positions, self.rotations, self.rows.reshape(-1)[np.asarray(flat_index)])


def point_geometry_posed(points: np.ndarray, pose_index: np.ndarray, poses: RowPoses, camera_mm: float | Any,
                         start: HeadPose | None = None, dtype: type = np.float64) -> PointGeometry:
    """:func:`point_geometry` with each point's own head pose (``poses``, ``pose_index`` (N,) into them).

    Each point is taken into the head frame of the profile that measured it; the laser and camera directions come
    from that frame, as in :func:`point_geometry` (the source on the point's head-Y line, the camera at
    ``camera_mm`` from it). ``u`` and ``standoff`` are in that frame; ``s`` (the position along the scan) is the
    head-Y coordinate in the frame of ``start`` (default: the first pose), as for a single-pose scan. For a pass in
    which every pose is ``start`` moved along its own +Y, the result equals :func:`point_geometry` from ``start``
    (within rounding).
    """
    pts = np.ascontiguousarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    idx = np.asarray(pose_index)
    if idx.shape != (len(pts),):
        raise ValueError(f"pose_index must have shape ({len(pts)},), got {idx.shape}")
    first = start if start is not None else poses.first()
    from .geometry_kernels import posed_geometry

    n = len(pts)
    out = np.empty((8, n), dtype=np.float64)  # L (3), V (3), source distance, x: one compiled pass, no GIL
    s64 = np.empty(n, dtype=np.float64)
    z = np.empty(n, dtype=np.float64)
    posed_geometry(pts, idx.astype(np.int64, copy=False), poses.positions, poses.rotations,
                   np.asarray(camera_vector(camera_mm), dtype=np.float64), first.position, first.rotation[:, 1].copy(),
                   out, z, s64)
    L: np.ndarray = np.ascontiguousarray(out[0:3].T, dtype=dtype)
    V: np.ndarray = np.ascontiguousarray(out[3:6].T, dtype=dtype)
    dist: np.ndarray = out[6].astype(dtype)
    x: np.ndarray = out[7].astype(dtype)
    z_out: np.ndarray = z.astype(dtype)
    s: np.ndarray = s64.astype(dtype)
    return PointGeometry(L=L, V=V, source_distance=dist, standoff=-z_out, u=x, s=s)


def rotation_xyz(rx: float, ry: float, rz: float) -> np.ndarray:
    """R = Rz(rz) · Ry(ry) · Rx(rx) (radians), a rotation in the head frame."""
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    r_x = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    r_y = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    r_z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return r_z @ r_y @ r_x


def xyz_angles(r: np.ndarray) -> tuple[float, float, float]:
    """The inverse of :func:`rotation_xyz`: (rx, ry, rz) radians with R = Rz(rz) · Ry(ry) · Rx(rx) — REP 103's roll,
    pitch, yaw about fixed X, Y, Z (ry in [−π/2, π/2])."""
    r = np.asarray(r, dtype=np.float64)
    return (float(np.arctan2(r[2, 1], r[2, 2])), float(np.arcsin(np.clip(-r[2, 0], -1.0, 1.0))),
            float(np.arctan2(r[1, 0], r[0, 0])))


def orientation_grid(max_tilt: float, tilt_steps: int, max_turn: float, turn_steps: int) -> list[np.ndarray]:
    """Head-frame rotations of the search; ``max_* <= 0`` or 1 step → that axis is not searched."""
    tilts = np.linspace(-max_tilt, max_tilt, tilt_steps) if max_tilt > 0 and tilt_steps > 1 else np.zeros(1)
    turns = np.linspace(-max_turn, max_turn, turn_steps) if max_turn > 0 and turn_steps > 1 else np.zeros(1)
    return [rotation_xyz(a, b, c) for c in turns for a in tilts for b in tilts]
