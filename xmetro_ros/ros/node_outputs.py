"""The node's outputs in bags: topic and type conventions, topic classification, loss accounting, reading the
outputs back per scan and comparing two runs field by field.

Shared by the offline ``xmetro predict`` and the live ``xmetro replay`` (neither imports the other). No DDS:
reading uses :class:`xmetro_ros.bag.reader.BagReader` and PointCloud2 decoding :mod:`xmetro_ros.ros.cloud`.
Lengths in metres (as on the topics) unless a name says ``_mm``.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..scan.targets import study_target
from .convert import m_to_mm, stamp_to_ns

__all__ = [
    "DIAGNOSTICS_TYPE",
    "EXACT",
    "OUTPUT_SUFFIXES",
    "POINTCLOUD2",
    "QUALITY_TYPE",
    "SETTINGS_TYPE",
    "TF_TYPE",
    "OutputSet",
    "Tolerance",
    "TopicError",
    "cdr_header",
    "classify_topics",
    "cloud_arrays",
    "compare_outputs",
    "describe_loss",
    "deviation_arrays",
    "quality_dict",
    "read_outputs",
]

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
SETTINGS_TYPE = "xmetro_ros/msg/ScannerSettings"
QUALITY_TYPE = "xmetro_ros/msg/ScanQuality"
TF_TYPE = "tf2_msgs/msg/TFMessage"
DIAGNOSTICS_TYPE = "diagnostic_msgs/msg/DiagnosticArray"
OUTPUT_SUFFIXES = ("/deviations", "/corrected", "/quality")

class TopicError(RuntimeError):
    """A bag's topics cannot be used as node input (a wanted topic missing or of the wrong type)."""


def describe_loss(report: Any) -> list[str]:
    """Lines for what BAG's reader could not deliver (``BagReport``: lost records, unfinished files, unknown types)."""
    if report is None or getattr(report, "ok", True):
        return []
    lines = [f"{n} messages of type {t} not installed here were skipped"
             for t, n in sorted(report.unknown_types.items())]
    lines += [f"{Path(f).name}: not closed by its writer (truncated?)" for f in report.unfinished_files]
    if report.recovered_from_partial_chunk:
        lines.append(f"{report.recovered_from_partial_chunk} messages recovered from a truncated chunk")
    lines += [lost.describe() for lost in report.lost]
    return lines


def classify_topics(topics: dict[str, str], wanted: list[str] | None = None) -> tuple[list[str], list[str]]:
    """(scan input topics, settings topics) of a bag with ``topics`` {name: type}.

    Raises:
        TopicError: a wanted topic is not in the bag or is not a PointCloud2.
    """
    settings = sorted(t for t, ty in topics.items() if ty == SETTINGS_TYPE)
    if wanted:
        norm = {t.lstrip("/"): t for t in topics}
        scans = []
        for w in wanted:
            t = norm.get(w.lstrip("/"))
            if t is None:
                raise TopicError(f"topic {w!r} is not in the bag (topics: {', '.join(sorted(topics)) or 'none'})")
            if topics[t] != POINTCLOUD2:
                raise TopicError(f"topic {t!r} has type {topics[t]}, not {POINTCLOUD2}")
            scans.append(t)
        return scans, settings
    scans = sorted(t for t, ty in topics.items() if ty == POINTCLOUD2 and not t.endswith(OUTPUT_SUFFIXES))
    return scans, settings


def cdr_header(raw: bytes, cloud: bool = False) -> tuple[int, str, int]:
    """(stamp ns, frame_id, width × height if ``cloud``) of a CDR message that starts with a std_msgs/Header.

    Read from the bytes (no deserialisation of the point data). Raises ValueError on a truncated/odd buffer.
    """
    if len(raw) < 16 or raw[0] != 0 or raw[1] not in (0, 1):
        raise ValueError("not a CDR buffer")
    e = "<" if raw[1] == 1 else ">"
    sec, nsec, n = struct.unpack_from(e + "iII", raw, 4)
    if 16 + n > len(raw):
        raise ValueError("CDR header string runs past the buffer")
    frame = bytes(raw[16:16 + n]).rstrip(b"\0").decode("utf-8", "replace")
    points = 0
    if cloud:
        off = 16 + n
        off += (-(off - 4)) % 4  # align to 4 relative to the payload start
        height, width = struct.unpack_from(e + "II", raw, off)
        points = int(height) * int(width)
    return int(sec) * 1_000_000_000 + int(nsec), frame, points


# ScanQuality fields that are not a function of the input (timing; the node's cumulative scan accounting).
_SKIP_QUALITY = {"processing_latency", "scans_received", "scans_judged", "scans_dropped", "scans_lost"}


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
        return stamp_to_ns(s)

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
            "flag_counts": dict(zip(list(q.flag_names), [int(c) for c in q.flag_counts], strict=True)),
            "mean_abs_error_mm": m_to_mm(np.asarray(q.mean_abs_error, dtype=float)).tolist(),
            "p95_abs_error_mm": m_to_mm(np.asarray(q.p95_abs_error, dtype=float)).tolist(),
            "usable_fraction": float(q.usable_fraction),
            "settings_defaulted": bool(q.settings_defaulted),
            "mean_uncertainty_mm": m_to_mm(np.asarray(q.mean_uncertainty, dtype=float)).tolist(),
            "p95_uncertainty_mm": m_to_mm(np.asarray(q.p95_uncertainty, dtype=float)).tolist(),
            "decision_rule": str(q.decision_rule),
            "decisions": {"conforming": int(q.points_conforming), "non_conforming": int(q.points_non_conforming),
                          "undecided": int(q.points_undecided)},
        }


def read_outputs(bag: str | Path, node_name: str = "xmetro_node") -> list[OutputSet]:
    """Group the node's outputs in ``bag`` per scan, in the order the qualities were written.

    The node publishes ``~/deviations`` (and ``~/corrected`` while it has a subscriber, e.g. the recorder) for every
    scan it could process (error code 0) and a ``~/quality`` for every scan; the clouds are matched to the quality
    with the same header (stamp, frame), in order.
    """
    from ..bag.reader import BagReader

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
    """Each field of a PointCloud2 as a flat numpy array in native byte order (fields with count > 1 as their
    sub-fields), decoded by :func:`xmetro_ros.ros.cloud.read_points`, the package's one PointCloud2 decoder."""
    from .cloud import read_points

    arr = read_points(msg)
    return {name: np.asarray(arr[name]) for name in arr.dtype.names or ()}


def _msg_to_dict(m: Any) -> Any:
    """An rclpy message as nested dicts / lists (arrays as lists)."""
    if hasattr(m, "get_fields_and_field_types"):
        return {k: _msg_to_dict(getattr(m, k)) for k in m.get_fields_and_field_types()}
    if isinstance(m, (list, tuple)) or hasattr(m, "tolist"):
        return [_msg_to_dict(x) for x in (m.tolist() if hasattr(m, "tolist") else m)]
    if isinstance(m, (bytes, bytearray)):
        return list(m)
    return m


def quality_dict(q: Any) -> dict[str, Any]:
    """ScanQuality as a plain dict (nested messages as dicts), without the timing field."""
    d = _msg_to_dict(q)
    for k in _SKIP_QUALITY:
        d.pop(k, None)
    return d


def _cmp_values(path: str, a: Any, b: Any, atol: float, diffs: list[str]) -> None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(a.keys() | b.keys()):  # diffs listed in one order in every process
            _cmp_values(f"{path}.{k}", a.get(k), b.get(k), atol, diffs)
    elif isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            diffs.append(f"{path}: length {len(a)} != {len(b)}")
            return
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
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
    for k in ("points_flagged", "flag_counts", "points_conforming", "points_non_conforming", "points_undecided"):
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


def compare_outputs(a: list[OutputSet], b: list[OutputSet], tol: Tolerance = EXACT,
                    clouds: tuple[str, ...] = ("deviations", "corrected")) -> list[str]:
    """Differences between two output sequences (same scans in the same order); empty list = equal.

    ``clouds``: which PointCloud2 outputs to compare (the goldens hold only the deviations)."""
    diffs: list[str] = []
    if len(a) != len(b):
        diffs.append(f"{len(a)} scans != {len(b)} scans")
    # Lengths may differ (reported above): compare the common prefix.
    for i, (x, y) in enumerate(zip(a, b, strict=False)):
        _cmp_quality(i, x.quality, y.quality, tol, diffs)
        for kind in clouds:
            _cmp_cloud(f"scan {i} {kind}", getattr(x, kind), getattr(y, kind), tol, diffs)
    return diffs


def deviation_arrays(msg: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (N, 3) mm, predictions (N, 3) mm, flags (N,) uint16) of a ``~/deviations`` cloud.

    The predictions come back in the package's internal sign, the model's target t = nominal − measured
    (``scan.targets.study_target`` of the published dx, dy, dz = measured − nominal): the sign of the simulator's
    errors (``Artifact.errors``) and of what ``parts.cad_judge.cad_deviation`` takes, so that our own tools compare
    like with like. A person reads the published sign; this is the one reader that turns it back."""
    a = cloud_arrays(msg)
    pts = m_to_mm(np.stack([a["x"], a["y"], a["z"]], axis=1))
    dev = study_target(m_to_mm(np.stack([a["dx"], a["dy"], a["dz"]], axis=1)))
    return pts, dev, np.asarray(a["flags"], dtype=np.uint16)
