"""Package types ⇄ ROS messages: Scan ⇄ PointCloud2, (ScanSettings, HeadPose) ⇄ ScannerSettings, stamps.

Units: inside the package millimetres and milliseconds (per-mm densities); on ROS topics SI (metres, seconds,
per-metre densities), REP 103 axes. Point coordinates and the length-valued per-point fields named in
:data:`LENGTH_FIELDS` are scaled by 1e-3 on the way out and 1e3 on the way in; other fields (intensity, line index,
time in seconds, flags, ...) pass unchanged. Organized scans (H, W, 3) become clouds of height H, width W and back.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Pose, Quaternion
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

from ..msg import ScannerSettings
from ..scan.geometry import HeadPose
from ..scan.part_pose import pose7_to_matrix_mm  # the one reader of a part pose (re-exported)
from ..scan.scan import Scan
from ..scan.scanner import ScanSettings, SettingsError
from .cloud import CloudFormatError, create_cloud_from_arrays, field_names, validate_cloud, xyz_fields

__all__ = [
    "LENGTH_FIELDS",
    "MM_PER_M",
    "cloud_to_scan",
    "m_to_mm",
    "mm_to_m",
    "ns_to_stamp",
    "pose7_to_matrix_mm",
    "pose_from_msg",
    "pose_to_msg",
    "scan_to_cloud",
    "settings_from_msg",
    "settings_to_msg",
    "stamp_to_ns",
]

MM_PER_M = 1000.0

#: Per-point fields holding lengths (mm inside, m on topics): ``u``/``s`` position along the laser line / scan
#: direction, ``standoff`` and ``source_distance`` (see geometry.PointGeometry), ``range``, and predicted or
#: expected deviations per axis ``dx, dy, dz`` / ``ex, ey, ez`` / ``expected_error_{x,y,z}``.
LENGTH_FIELDS: frozenset[str] = frozenset(
    {"u", "s", "standoff", "source_distance", "range", "dx", "dy", "dz", "ex", "ey", "ez",
     "expected_error_x", "expected_error_y", "expected_error_z"}
)

_NS = 1_000_000_000


M_PER_MM = 1e-3


def mm_to_m(value: Any) -> Any:
    """Millimetres (core) → metres (topics): numbers stay numbers, sequences and arrays become float64 arrays.

    A multiplication by 1e-3 (not a division by 1000): the published values are bit-identical to the goldens."""
    if isinstance(value, (int, float, np.number)):
        return float(value) * M_PER_MM
    return np.asarray(value, dtype=np.float64) * M_PER_MM


def m_to_mm(value: Any) -> Any:
    """Metres (topics) → millimetres (core): numbers stay numbers, sequences and arrays become float64 arrays."""
    if isinstance(value, (int, float, np.number)):
        return float(value) * MM_PER_M
    return np.asarray(value, dtype=np.float64) * MM_PER_M


def stamp_to_ns(stamp: Time) -> int:
    """builtin_interfaces/Time → integer nanoseconds."""
    return int(stamp.sec) * _NS + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> Time:
    """Integer nanoseconds (≥ 0) → builtin_interfaces/Time.

    Raises:
        ValueError: negative or beyond the int32 seconds range of the message.
    """
    ns = int(ns)
    if ns < 0 or ns // _NS > 2**31 - 1:
        raise ValueError(f"stamp {ns} ns is outside the range of builtin_interfaces/Time")
    return Time(sec=ns // _NS, nanosec=ns % _NS)


def pose_to_msg(pose: HeadPose) -> Pose:
    """HeadPose (mm) → geometry_msgs/Pose (m)."""
    p = pose.position / MM_PER_M
    q = pose.quaternion
    return Pose(
        position=Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
        orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
    )


def pose_from_msg(msg: Pose) -> HeadPose:
    """geometry_msgs/Pose (m) → HeadPose (mm); the quaternion is normalised.

    Raises:
        SettingsError: non-finite position, zero or non-finite quaternion.
    """
    pos = np.array([msg.position.x, msg.position.y, msg.position.z], dtype=float)
    q = np.array([msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w], dtype=float)
    if not np.isfinite(pos).all():
        raise SettingsError(f"head_pose position {pos.tolist()} is not finite")
    try:
        return HeadPose.from_quaternion(pos * MM_PER_M, q)
    except ValueError as e:
        raise SettingsError(f"head_pose orientation is invalid: {e}") from e


def settings_to_msg(
    settings: ScanSettings,
    pose: HeadPose,
    frame_id: str = "artifact",
    stamp_ns: int = 0,
    scanner_id: str = "",
) -> ScannerSettings:
    """(ScanSettings mm/ms, HeadPose mm) → ScannerSettings (per metre, seconds, metres)."""
    si = settings.to_si()
    return ScannerSettings(
        header=Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame_id),
        scanner_id=scanner_id,
        lateral_density=si["lateral_density"],
        direction_density=si["direction_density"],
        exposure_time=si["exposure_time"],
        head_pose=pose_to_msg(pose),
    )


def settings_from_msg(
    msg: ScannerSettings, ranges: dict[str, tuple[float, float]] | None = None
) -> tuple[ScanSettings, HeadPose, str, str, int]:
    """ScannerSettings → (ScanSettings mm/ms, HeadPose mm, scanner_id, frame_id, stamp_ns).

    Args:
        msg: the message (SI units).
        ranges: optional scanner ranges (``ScannerModel.settings_range``, mm/ms units) to check against.

    Raises:
        SettingsError: a density or the exposure missing (0), negative or not finite, out of ``ranges``, or an
            invalid head pose.
    """
    for name in ("lateral_density", "direction_density", "exposure_time"):
        v = getattr(msg, name)
        if not math.isfinite(v) or v <= 0:
            raise SettingsError(f"ScannerSettings.{name} must be a positive finite SI value, got {v!r}")
    settings = ScanSettings.from_si(msg.lateral_density, msg.direction_density, msg.exposure_time)
    settings.validate(ranges)
    return settings, pose_from_msg(msg.head_pose), msg.scanner_id, msg.header.frame_id, stamp_to_ns(msg.header.stamp)


def _header(scan: Scan, header_stamp: Time | int | None) -> Header:
    if header_stamp is None:
        stamp = ns_to_stamp(scan.stamp_ns)
    elif isinstance(header_stamp, Time):
        stamp = header_stamp
    else:
        stamp = ns_to_stamp(int(header_stamp))
    return Header(stamp=stamp, frame_id=scan.frame_id)


def scan_to_cloud(
    scan: Scan, header_stamp: Time | int | None = None, *, fields: Iterable[str] | None = None
) -> PointCloud2:
    """Scan (mm) → PointCloud2 (m): float32 x, y, z, then the scan's fields in their order.

    Float fields are sent as float32 (fields in :data:`LENGTH_FIELDS` scaled to metres); integer and bool fields
    keep their type (bool → uint8). Organized scans give height H, width W with NaN placeholders kept
    (``is_dense`` false when any point is NaN).

    Args:
        scan: the scan.
        header_stamp: stamp of the header (Time or ns); default ``scan.stamp_ns``.
        fields: names of the scan fields to include (default: all).
    """
    shape = scan.shape
    n = int(np.prod(shape))
    pts = np.asarray(scan.points).reshape(n, 3)
    arrays: dict[str, np.ndarray] = {}
    for i, axis in enumerate("xyz"):
        arrays[axis] = (pts[:, i] / MM_PER_M).astype(np.float32)
    names = list(scan.fields) if fields is None else list(fields)
    for name in names:
        if name in ("x", "y", "z"):
            raise ValueError(f"scan field {name!r} clashes with a coordinate")
        if name not in scan.fields:
            raise KeyError(f"scan has no field {name!r} (fields: {list(scan.fields)})")
        a: np.ndarray = np.asarray(scan.fields[name]).reshape(n)
        if a.dtype.kind == "f":
            a = (a / MM_PER_M if name in LENGTH_FIELDS else a).astype(np.float32)
        arrays[name] = a
    height, width = (shape[0], shape[1]) if scan.organized else (1, n)
    return create_cloud_from_arrays(_header(scan, header_stamp), arrays, height=height, width=width)


def _to_mm(a: np.ndarray) -> np.ndarray:
    """Length field m → mm in its own float type, or in float64 when a finite float32 value would overflow (> 3.4e35
    m), so that decoding never turns a finite value into Inf."""
    with np.errstate(over="ignore", invalid="ignore"):
        mm = a * MM_PER_M
    if a.dtype == np.float32 and np.isinf(mm).sum() != np.isinf(a).sum():
        mm = a.astype(np.float64) * MM_PER_M
    return mm


def cloud_to_scan(
    msg: PointCloud2,
    settings: ScanSettings,
    pose: HeadPose,
    scanner_id: str,
    extra_fields: Iterable[str] | None = None,
    **scan_kwargs: Any,
) -> Scan:
    """PointCloud2 (m) → Scan (mm, float64 points), organized when ``height > 1``.

    Args:
        msg: the cloud; validated (layout and x/y/z; NaN points allowed, kept as NaN).
        settings, pose, scanner_id: what the scan was taken with (see :func:`settings_from_msg`).
        extra_fields: cloud fields to keep as scan fields (default: every field but x, y, z; count > 1 fields as
            ``name_i``). Fields in :data:`LENGTH_FIELDS` are converted to mm; integer fields become float64.
        scan_kwargs: passed to :class:`Scan` (artifact, meta, ...).

    Raises:
        CloudFormatError: malformed cloud, or a requested extra field is absent or has count > 1
            (``MISSING_INPUT_FIELD``); no other exception for any cloud content.
    """
    validate_cloud(msg, require_valid_points=False)  # O(fields) layout checks before anything is read
    if extra_fields is None:
        extra_fields = [k for k in field_names(msg) if k not in ("x", "y", "z")]
    xyz, extras = xyz_fields(msg, list(extra_fields))
    h, w = int(msg.height), int(msg.width)
    lead = (h, w) if h > 1 else (h * w,)
    # Values are kept as they are, absurd ones included (3e38 m stays 3e41 mm, finite): judging them is the node's
    # job. Only float64 beyond ±1.8e305 m overflows to ±Inf in mm (then a non-finite point like any other).
    with np.errstate(over="ignore"):
        points = (xyz.astype(np.float64) * MM_PER_M).reshape(*lead, 3)
    fields = {}
    for name, a in extras.items():
        if a.ndim != 1:
            raise CloudFormatError(
                "MISSING_INPUT_FIELD", f"field {name!r} has count > 1; request its sub-fields {name}_0, ..."
            )
        if name in LENGTH_FIELDS:
            a = _to_mm(a)
        else:
            a = a.copy()
        fields[name] = a.reshape(lead)
    return Scan(
        points=points,
        settings=settings,
        pose=pose,
        scanner_id=scanner_id,
        fields=fields,
        frame_id=msg.header.frame_id,
        stamp_ns=stamp_to_ns(msg.header.stamp),
        **scan_kwargs,
    )
