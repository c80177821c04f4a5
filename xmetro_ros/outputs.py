"""The node's per-scan outputs as read back from a bag, and their field-by-field comparison (ROS messages, no DDS).

Used by ``xmetro predict`` (which writes them), the golden-output tests and the demo report:

- :func:`read_outputs`: ``~/quality``, ``~/deviations``, ``~/corrected`` of one node from an MCAP / rosbag2 bag,
  grouped per scan (:class:`OutputSet`).
- :func:`compare_outputs`: every field of ScanQuality (except ``processing_latency``, a wall-clock time) and of
  the two PointCloud2 (header, layout, then each point field decoded: floats within ``atol`` with NaN == NaN,
  integers exact up to a stated share of mismatching points); returns the list of differences (empty = same).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["OutputSet", "Tolerance", "read_outputs", "compare_outputs", "cloud_arrays", "quality_dict", "EXACT"]

# PointField datatype → numpy dtype (sensor_msgs/PointField constants 1..8).
_PF_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
# ScanQuality fields that are not a function of the input (timing).
_SKIP_QUALITY = {"processing_latency"}


@dataclass(frozen=True)
class Tolerance:
    """Comparison tolerance. Lengths in metres (as on the topics)."""

    deviation_atol_m: float = 0.0
    quality_atol_m: float = 0.0
    fraction_atol: float = 0.0
    flags_max_mismatch_fraction: float = 0.0

    @classmethod
    def from_dict(cls, d: dict[str, float]) -> Tolerance:
        return cls(**{k: float(v) for k, v in d.items() if k in cls.__dataclass_fields__})


EXACT = Tolerance()


@dataclass
class OutputSet:
    """The outputs of the node for one scan (deviations / corrected are None when the scan was in ERROR)."""

    quality: Any
    deviations: Any | None = None
    corrected: Any | None = None

    @property
    def stamp_ns(self) -> int:
        s = self.quality.header.stamp
        return int(s.sec) * 1_000_000_000 + int(s.nanosec)

    def summary_dict(self) -> dict[str, Any]:
        """JSON-able per-scan summary (mm for errors)."""
        q = self.quality
        return {
            "stamp_ns": self.stamp_ns,
            "frame_id": q.header.frame_id,
            "verdict": int(q.verdict),
            "error_code": int(q.error_code),
            "message": q.message,
            "points_received": int(q.points_received),
            "points_valid": int(q.points_valid),
            "points_flagged": int(q.points_flagged),
            "flag_counts": dict(zip(list(q.flag_names), [int(c) for c in q.flag_counts])),
            "mean_abs_error_mm": [float(v) * 1e3 for v in q.mean_abs_error],
            "p95_abs_error_mm": [float(v) * 1e3 for v in q.p95_abs_error],
            "usable_fraction": float(q.usable_fraction),
            "settings_defaulted": bool(q.settings_defaulted),
        }


def read_outputs(bag: str | Path, node_name: str = "xmetro_node") -> list[OutputSet]:
    """Group the node's outputs in ``bag`` per scan, in the order the qualities were written.

    The node publishes ``~/deviations`` and ``~/corrected`` for every scan it could process (error code 0) and a
    ``~/quality`` for every scan; the clouds are matched to the quality with the same header (stamp, frame), in order.
    """
    from .bag.reader import BagReader

    ns = "/" + node_name.strip("/")
    names = {f"{ns}/quality": "quality", f"{ns}/deviations": "deviations", f"{ns}/corrected": "corrected"}
    qualities: list[Any] = []
    clouds: dict[str, list[Any]] = {"deviations": [], "corrected": []}
    for m in BagReader(Path(bag)).messages(topics=list(names)):
        kind = names.get(m.topic)
        if kind == "quality":
            qualities.append(m.msg)
        elif kind is not None:
            clouds[kind].append(m.msg)
    out = []
    used = {"deviations": 0, "corrected": 0}
    for q in qualities:
        o = OutputSet(q)
        if int(q.error_code) == 0:
            key = (q.header.stamp.sec, q.header.stamp.nanosec, q.header.frame_id)
            for kind in ("deviations", "corrected"):
                lst = clouds[kind]
                i = used[kind]
                # Take the next cloud with this header (skipping none normally).
                while i < len(lst) and (lst[i].header.stamp.sec, lst[i].header.stamp.nanosec,
                                        lst[i].header.frame_id) != key:
                    i += 1
                if i < len(lst):
                    setattr(o, kind, lst[i])
                    used[kind] = i + 1
        out.append(o)
    return out


def cloud_arrays(msg: Any) -> dict[str, np.ndarray]:
    """Each PointField of a PointCloud2 as a flat numpy array (count 1 fields; endianness honoured)."""
    n = int(msg.width) * int(msg.height)
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for f in msg.fields:
        names.append(f.name)
        formats.append((order + _PF_DTYPES[int(f.datatype)], (int(f.count),)) if int(f.count) > 1
                       else order + _PF_DTYPES[int(f.datatype)])
        offsets.append(int(f.offset))
    dt = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": int(msg.point_step)})
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    if int(msg.row_step) == int(msg.point_step) * int(msg.width):
        arr = data[: n * dt.itemsize].view(dt)
    else:  # padded rows
        rows = data.reshape(int(msg.height), int(msg.row_step))[:, : int(msg.point_step) * int(msg.width)]
        arr = np.ascontiguousarray(rows).view(dt).reshape(-1)
    return {name: np.asarray(arr[name]).reshape(n, -1).squeeze(-1) if arr[name].ndim == 1 else arr[name]
            for name in names}


def quality_dict(q: Any) -> dict[str, Any]:
    """ScanQuality as a plain dict (nested settings flattened), without the timing field."""
    from rosidl_runtime_py import message_to_ordereddict

    d = message_to_ordereddict(q)
    for k in _SKIP_QUALITY:
        d.pop(k, None)
    return d


def _cmp_values(path: str, a: Any, b: Any, atol: float, diffs: list[str]) -> None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in a.keys() | b.keys():
            _cmp_values(f"{path}.{k}", a.get(k), b.get(k), atol, diffs)
    elif isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            diffs.append(f"{path}: length {len(a)} != {len(b)}")
            return
        for i, (x, y) in enumerate(zip(a, b)):
            _cmp_values(f"{path}[{i}]", x, y, atol, diffs)
    elif isinstance(a, float) or isinstance(b, float):
        if not (a == b or (np.isnan(a) and np.isnan(b)) or abs(float(a) - float(b)) <= atol):
            diffs.append(f"{path}: {a!r} != {b!r} (atol {atol:g})")
    elif a != b:
        diffs.append(f"{path}: {a!r} != {b!r}")


def _cmp_quality(i: int, a: Any, b: Any, tol: Tolerance, diffs: list[str]) -> None:
    da, db = quality_dict(a), quality_dict(b)
    # Counts derived from flags may differ by the allowed flag mismatches.
    n = max(1, int(a.points_received))
    slack = int(np.floor(tol.flags_max_mismatch_fraction * n))
    for k in ("points_flagged", "flag_counts"):
        va, vb = np.atleast_1d(da.pop(k)), np.atleast_1d(db.pop(k))
        if va.shape != vb.shape or np.any(np.abs(va.astype(np.int64) - vb.astype(np.int64)) > slack):
            diffs.append(f"scan {i} quality.{k}: {va.tolist()} != {vb.tolist()} (slack {slack})")
    for k in ("usable_fraction",):
        if abs(da.pop(k) - db.pop(k)) > tol.fraction_atol:
            diffs.append(f"scan {i} quality.{k}: {a.usable_fraction!r} != {b.usable_fraction!r}")
    # The verdict reason quotes fractions: compare it only when no tolerance is allowed.
    if tol.flags_max_mismatch_fraction > 0 or tol.fraction_atol > 0:
        da.pop("message", None)
        db.pop("message", None)
    _cmp_values(f"scan {i} quality", da, db, tol.quality_atol_m, diffs)


def _cmp_cloud(label: str, a: Any, b: Any, tol: Tolerance, diffs: list[str]) -> None:
    if (a is None) != (b is None):
        diffs.append(f"{label}: present in one output only")
        return
    if a is None:
        return
    for k in ("height", "width", "point_step", "row_step", "is_bigendian", "is_dense"):
        if getattr(a, k) != getattr(b, k):
            diffs.append(f"{label}.{k}: {getattr(a, k)!r} != {getattr(b, k)!r}")
    if (a.header.stamp.sec, a.header.stamp.nanosec, a.header.frame_id) != (
            b.header.stamp.sec, b.header.stamp.nanosec, b.header.frame_id):
        diffs.append(f"{label}.header differs")
    fa = [(f.name, f.offset, f.datatype, f.count) for f in a.fields]
    fb = [(f.name, f.offset, f.datatype, f.count) for f in b.fields]
    if fa != fb:
        diffs.append(f"{label}.fields: {fa} != {fb}")
        return
    xa, xb = cloud_arrays(a), cloud_arrays(b)
    n = max(1, int(a.width) * int(a.height))
    for name in xa:
        va, vb = xa[name], xb[name]
        if va.dtype.kind == "f":
            # x, y, z are the scan's points: exact; the rest are predictions: within the tolerance.
            atol = 0.0 if name in ("x", "y", "z") and label.endswith("deviations") else tol.deviation_atol_m
            same = np.isclose(va.astype(np.float64), vb.astype(np.float64), rtol=0.0, atol=atol, equal_nan=True)
            if not same.all():
                j = int(np.flatnonzero(~same)[0])
                diffs.append(f"{label}.{name}: {int((~same).sum())} points differ (first #{j}: {va[j]!r} vs "
                             f"{vb[j]!r}, atol {atol:g} m)")
        else:
            bad = int(np.count_nonzero(va != vb))
            if bad > np.floor(tol.flags_max_mismatch_fraction * n):
                diffs.append(f"{label}.{name}: {bad} of {n} points differ")


def compare_outputs(a: list[OutputSet], b: list[OutputSet], tol: Tolerance = EXACT) -> list[str]:
    """Differences between two output sequences (same scans in the same order); empty list = equal."""
    diffs: list[str] = []
    if len(a) != len(b):
        diffs.append(f"{len(a)} scans != {len(b)} scans")
    for i, (x, y) in enumerate(zip(a, b)):
        _cmp_quality(i, x.quality, y.quality, tol, diffs)
        _cmp_cloud(f"scan {i} deviations", x.deviations, y.deviations, tol, diffs)
        _cmp_cloud(f"scan {i} corrected", x.corrected, y.corrected, tol, diffs)
    return diffs
