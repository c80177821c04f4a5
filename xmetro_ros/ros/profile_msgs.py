"""One line-scanner profile message (``sensor_msgs/PointCloud2``, height 1) → the ROS-free
:class:`~xmetro_ros.scan.assembly.Profile` the :class:`~xmetro_ros.scan.assembly.ProfileAssembler` takes.

What drivers publish (docs/profile-streams.md, "Driver layouts"; emulated byte for byte in
``test/driver_emulators.py``): one cloud per profile, height 1, width = the points of that profile, in the sensor frame
(x along the laser line, z the range), metres, float32 x, y, z at offsets 0/4/8 followed by padding or extra fields of
any PointField datatype (intensity, width, threshold, m0, m1, rgb, ...). A point without a return is marked by the
driver's own convention: z = +inf (scanCONTROL sam-xl/scancontrol, Keyence keyence_experimental), NaN, dropped from
the message (then the width changes from profile to profile and the dropped points' columns are lost), or not at all
(IGMR-RWTH/scancontrol_lls passes the SDK's out-of-range value, z ≈ 32.2 mm, through: ``min_range_m`` below).
``is_dense`` is left true by several of them whatever the data holds (pcl's default): it is ignored here.

Decoding: the layout is checked as :func:`~xmetro_ros.ros.cloud.validate_cloud` does, once (a malformed message raises
:class:`~xmetro_ros.ros.cloud.CloudFormatError` with its ``code``, nothing else escapes); x, y, z and the extra
fields come from :func:`~xmetro_ros.ros.cloud.xyz_fields`. A point with a non-finite coordinate (+inf, −inf, NaN),
or with z below ``min_range_m``, becomes a NaN row (no return, position in the line kept); other values are kept as
they are (y included: a driver that writes an encoder position into y keeps it). Units are not converted (metres, as
:class:`Profile` wants).

Copies: with ``dtype=None`` the points are a **view** of ``msg.data`` (no copy) when every point is a return and
x, y, z are consecutive native floats (every layout above), else one copy with the NaN rows written; extra float
fields are strided views, integer fields float64 copies. The profile then shares the message's buffer: do not
reuse the message. ``dtype=np.float64`` gives float64 points (one copy; float32 values are exact in float64).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from numpy.typing import DTypeLike
from sensor_msgs.msg import PointCloud2, PointField

from ..scan.assembly import Profile
from .cloud import CloudFormatError, _check_layout, xyz_fields
from .convert import stamp_to_ns

__all__ = ["no_return_mask", "profile_from_cloud"]

_XYZ = ("x", "y", "z")


def no_return_mask(points: np.ndarray, min_range_m: float | None = None) -> np.ndarray:
    """(W,) bool: the points without a return — a non-finite coordinate, or z below ``min_range_m`` when given."""
    with np.errstate(invalid="ignore"):
        # per column: a reduce over axis 1 of a strided (W, 3) view costs 5x more
        bad = ~(np.isfinite(points[:, 0]) & np.isfinite(points[:, 1]) & np.isfinite(points[:, 2]))
        if min_range_m is not None:
            bad |= points[:, 2] < min_range_m
    return bad


def _no_return_at_all(msg: PointCloud2) -> bool:
    """A driver that drops no-returns sends a profile without any as height 1, width 0, no data, its fields
    declared: a profile with no return, not a malformed cloud. (A cloud without float x, y, z stays an error.)"""
    if int(msg.width) != 0 or int(msg.height) > 1 or len(msg.data) != 0:
        return False
    kinds = {f.name: int(f.datatype) for f in msg.fields}
    return all(kinds.get(n) in (PointField.FLOAT32, PointField.FLOAT64) for n in _XYZ)


def profile_from_cloud(
    msg: PointCloud2,
    *,
    fields: Iterable[str] | None = None,
    min_range_m: float | None = None,
    dtype: DTypeLike | None = None,
) -> Profile:
    """A profile message → :class:`Profile` (stamp ns, frame_id, points (W, 3) sensor frame m, fields (W,) float).

    Args:
        msg: the profile: height 1 (an organized cloud is a batch of profiles or an area scan: use
            :func:`~xmetro_ros.ros.convert.cloud_to_scan`).
        fields: extra fields to carry (default: every field but x, y, z; a count > 1 field as ``name_0``, ...).
        min_range_m: points with z below it are no return (the driver's out-of-range value passed through, e.g.
            ~0.0322 m from the scanCONTROL SDK on IGMR-RWTH/scancontrol_lls); None: only non-finite points are.
        dtype: float type of the points; None keeps the message's (a zero-copy view where possible).

    Raises:
        CloudFormatError: a malformed layout (``EMPTY_CLOUD``, ``BAD_LAYOUT``, ``DUPLICATE_FIELD``), x/y/z missing or
            not floating point (``MISSING_FIELD``), a requested field absent (``MISSING_INPUT_FIELD``), height > 1
            (``BAD_LAYOUT``). A profile without any return is not an error: its points are all NaN, or none at all
            from a driver that drops no-returns (width 0, float x, y, z declared).
    """
    if not isinstance(msg, PointCloud2):
        raise TypeError("msg is not a sensor_msgs.msg.PointCloud2")
    if _no_return_at_all(msg):
        return Profile(stamp_ns=stamp_to_ns(msg.header.stamp), frame_id=msg.header.frame_id,
                       points=np.zeros((0, 3), dtype=np.float64 if dtype is None else dtype), fields={})
    checked = _check_layout(msg)  # once: xyz_fields reuses it (a 1 kHz stream pays for it on every profile)
    if int(msg.height) != 1:
        raise CloudFormatError(
            "BAD_LAYOUT",
            f"a profile has height 1, this cloud is organized ({msg.height} × {msg.width}): a batch of profiles or an "
            "area scan (use cloud_to_scan)",
        )
    names = [n for f in checked for n in f.sub_names() if n not in _XYZ] if fields is None else list(fields)
    for n in names:
        if n in _XYZ:
            raise CloudFormatError("MISSING_INPUT_FIELD", f"field {n!r} is a coordinate, not an extra field")
    xyz, extras = xyz_fields(msg, names, _checked_fields=checked)
    bad = no_return_mask(xyz, min_range_m)
    want = xyz.dtype if dtype is None else np.dtype(dtype)
    if want.kind != "f":
        raise ValueError(f"dtype must be a float type, got {want}")
    any_bad = bool(bad.any())
    points = xyz.astype(want, copy=any_bad or want != xyz.dtype)
    if any_bad:
        points[bad] = np.nan
    out: dict[str, np.ndarray] = {}
    for n, a in extras.items():
        if a.ndim != 1:
            raise CloudFormatError("MISSING_INPUT_FIELD", f"field {n!r} has count > 1; request {n}_0, {n}_1, ...")
        out[n] = a
    return Profile(stamp_ns=stamp_to_ns(msg.header.stamp), frame_id=msg.header.frame_id, points=points, fields=out)
