"""`xmetro predict BAG --out OUT.mcap`: the live node's processing, offline, in batch (no DDS); and the node's
outputs read back from bags and compared field by field.

Predict runs :class:`xmetro_ros.node.XmetroCore` — the very object the live node runs in its worker — over the
bag's messages in order: each ScannerSettings message goes to its settings history, each PointCloud2 of the input
topics is judged (``XmetroCore.judge``), and the resulting ``~/quality``, ``~/deviations`` and ``~/corrected``
messages are written under the node's topic names (``/xmetro_node/...``), next to the inputs (``/scan``,
``/scanner_settings``), exactly as ``xmetro replay --record`` records a live run. So both can be read with
:func:`read_outputs` and compared with :func:`compare_outputs`: they are identical field by field except
``ScanQuality.processing_latency`` (wall-clock time; offline = the computing time). Node parameters: the defaults
of :mod:`xmetro_ros.node_params`, ``--model`` and ``--param name=value`` overrides.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "EXACT",
    "OutputSet",
    "PredictError",
    "PredictResult",
    "Tolerance",
    "cloud_arrays",
    "compare_outputs",
    "deviation_arrays",
    "node_values",
    "predict_bag",
    "quality_dict",
    "read_outputs",
    "register",
    "run",
]

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
            "flag_counts": dict(zip(list(q.flag_names), [int(c) for c in q.flag_counts], strict=True)),
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
        for k in a.keys() | b.keys():
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
    """(points (N, 3) mm, predicted deviations (N, 3) mm, flags (N,) uint16) of a ``~/deviations`` cloud."""
    a = cloud_arrays(msg)
    pts = np.stack([a["x"], a["y"], a["z"]], axis=1).astype(np.float64) * 1e3
    dev = np.stack([a["dx"], a["dy"], a["dz"]], axis=1).astype(np.float64) * 1e3
    return pts, dev, np.asarray(a["flags"], dtype=np.uint16)


# --------------------------------------------------------------------------------------------- offline predict
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
SETTINGS_TYPE = "xmetro_ros/msg/ScannerSettings"


class PredictError(RuntimeError):
    """The bag cannot be processed offline (no scans, model unavailable, bad parameter)."""


@dataclass
class PredictResult:
    """What ``predict_bag`` did."""

    bag: str
    out: Path
    model_id: str
    outputs: list[OutputSet] = field(default_factory=list)
    inputs: list[str] = field(default_factory=list)  # input topic of each scan
    settings_seen: int = 0
    notes: list[str] = field(default_factory=list)
    losses: list[str] = field(default_factory=list)
    wall_s: float = 0.0

    def summary(self) -> str:
        from .replay import VERDICT_NAMES

        n_def = sum(1 for o in self.outputs if o.quality.settings_defaulted)
        lines = [f"predict {self.bag} → {self.out}: {len(self.outputs)} scans, {self.settings_seen} settings, "
                 f"model {self.model_id or '(none)'}, {n_def} with defaulted settings, {self.wall_s:.2f} s"]
        for i, (o, topic) in enumerate(zip(self.outputs, self.inputs, strict=True)):
            q = o.quality
            err = f" error_code={int(q.error_code)}" if int(q.error_code) else ""
            mae = ", ".join(f"{v * 1e3:.4f}" for v in q.mean_abs_error)
            lines.append(f"#{i:<3d} {topic:<20s} stamp={o.stamp_ns / 1e9:.3f}s points={q.points_received} -> "
                         f"{VERDICT_NAMES.get(int(q.verdict), '?')}{err} valid={q.points_valid} "
                         f"usable={q.usable_fraction:.3f} mean|e|(x,y,z)=({mae}) mm"
                         + (" settings DEFAULTED" if q.settings_defaulted else "")
                         + (f" — {q.message}" if q.message else ""))
        lines += [f"note: {n}" for n in self.notes]
        lines += [f"LOSS: {x}" for x in self.losses]
        return "\n".join(lines)


def node_values(model_dir: str | Path | None = None, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The node's parameter values: defaults of :data:`node_params.PARAMS`, then ``overrides``, then ``model_dir``.

    Raises:
        PredictError: unknown parameter, wrong type or a value the node would refuse.
    """
    from . import node_params

    specs = {p.name: p for p in node_params.PARAMS}
    values = {p.name: p.default for p in node_params.PARAMS}
    for k, v in (overrides or {}).items():
        if k not in specs:
            raise PredictError(f"unknown node parameter {k!r}")
        d = specs[k].default
        try:
            if isinstance(d, bool):
                v = v if isinstance(v, bool) else str(v).lower() in ("1", "true", "yes")
            elif isinstance(d, int):
                v = int(v)
            elif isinstance(d, float):
                v = float(v)
            else:
                v = str(v)
        except ValueError as e:
            raise PredictError(f"parameter {k}: {e}") from e
        values[k] = v
    if model_dir is not None:
        values["model_dir"] = str(Path(model_dir).resolve())
    reason = node_params.validate(values, values)
    if reason:
        raise PredictError(f"invalid parameter: {reason}")
    return values


def _recorded_qos(reader: Any, topics: list[str]) -> list[dict[str, Any]]:
    """The offered QoS profiles the source bag recorded for ``topics`` (v9 mappings, duplicates merged); [] when
    it recorded none or something unreadable (then the caller uses the live default)."""
    from .bag.qos import offered_qos_list

    out: list[dict[str, Any]] = []
    for t in topics:
        try:
            profiles = offered_qos_list(reader.offered_qos(t))
        except Exception:  # malformed YAML or profiles in someone else's bag: fall back to the live default
            continue
        out += [p for p in profiles if p not in out]
    return out


def predict_bag(
    bag: str | Path,
    out: str | Path,
    *,
    model_dir: str | Path | None = None,
    params: dict[str, Any] | None = None,
    topics: list[str] | None = None,
    node_name: str = "xmetro_node",
    log: Any = None,
    include: tuple[str, ...] = ("inputs", "deviations", "corrected"),
) -> PredictResult:
    """Judge every scan of ``bag`` as the live node would and write the outputs to ``out`` (.mcap).

    Args:
        bag: .mcap file or rosbag2 directory.
        out: output .mcap (must not exist).
        model_dir: model set directory (default: the shipped default model).
        params: node parameter overrides (SI units, as in config/xmetro.yaml).
        topics: PointCloud2 topics to judge (default: all but node outputs, as ``xmetro replay``).
        node_name: the node name used for the output topics.
        log: callable for one line per scan.
        include: what to write besides ``~/quality``: ``inputs`` (/scan, /scanner_settings), ``deviations``,
            ``corrected`` (the goldens keep only quality and deviations).

    Raises:
        PredictError: no model (the reason), no input scans. FileNotFoundError / BagFormatError: unreadable bag.
        FileExistsError: ``out`` exists.
    """
    from .bag import qos_profiles
    from .bag.reader import BagReader
    from .bag.writer import BagWriter
    from .node import XmetroCore
    from .replay import QUALITY_TYPE, ReplayError, classify_topics, describe_loss

    t_start = time.monotonic()
    if Path(out).exists():
        raise FileExistsError(f"output {out} already exists")
    values = node_values(model_dir, params)
    bag = Path(bag)
    reader = BagReader(bag)
    bag_topics = reader.topics()
    try:
        scan_topics, settings_topics = classify_topics(bag_topics, topics)
    except ReplayError as e:
        raise PredictError(str(e)) from e
    if not scan_topics:
        raise PredictError(f"bag {bag} has no {POINTCLOUD2} input topic (topics: "
                           + (", ".join(f"{t} [{ty}]" for t, ty in sorted(bag_topics.items())) or "none") + ")")
    core = XmetroCore(values, logger=None)
    if core.model is None:
        raise PredictError(f"no usable model: {core.degraded}")
    out = Path(out)
    res = PredictResult(bag=str(bag), out=out, model_id=core.model_id)
    if not settings_topics:
        res.notes.append(f"the bag has no {SETTINGS_TYPE} messages: every scan used the configured default settings "
                         f"(default_* parameters, head {core.scanner.standoff_mm:g} mm above the frame origin, "
                         "looking down); ScanQuality.settings_defaulted = true")
    ns = "/" + node_name.strip("/")
    out_topics = {"quality": f"{ns}/quality", "deviations": f"{ns}/deviations", "corrected": f"{ns}/corrected"}
    with BagWriter(out, compression="zstd") as w:
        # Inputs as recorded in the source bag (else as a live scanner offers them); outputs as the node offers them.
        w.add_topic("/scan", POINTCLOUD2, _recorded_qos(reader, scan_topics) or [qos_profiles.CLOUD])
        w.add_topic("/scanner_settings", SETTINGS_TYPE,
                    _recorded_qos(reader, settings_topics) or [qos_profiles.SETTINGS])
        w.add_topic(out_topics["quality"], QUALITY_TYPE, [qos_profiles.output()])
        w.add_topic(out_topics["deviations"], POINTCLOUD2, [qos_profiles.cloud_output()])
        w.add_topic(out_topics["corrected"], POINTCLOUD2, [qos_profiles.cloud_output()])
        for m in reader.messages(topics=set(scan_topics) | set(settings_topics)):
            if m.topic in settings_topics:
                err = core.add_settings(m.msg)
                res.settings_seen += 1
                if "inputs" in include:
                    w.write("/scanner_settings", m.raw, m.log_time_ns)
                if err:
                    res.notes.append(f"invalid ScannerSettings at log time {m.log_time_ns} ns: {err}")
                continue
            if "inputs" in include:
                w.write("/scan", m.raw, m.log_time_ns)
            o = core.judge(m.msg)
            for kind in ("deviations", "corrected"):
                if kind in include and getattr(o, kind) is not None:
                    w.write(out_topics[kind], getattr(o, kind), m.log_time_ns)
            w.write(out_topics["quality"], o.quality, m.log_time_ns)
            res.outputs.append(OutputSet(o.quality, o.deviations, o.corrected))
            res.inputs.append(m.topic)
            if log is not None:
                log(f"#{len(res.outputs) - 1} {m.topic}: {o.log}")
    res.losses = describe_loss(reader.report)
    res.wall_s = time.monotonic() - t_start
    return res


def _parse_params(items: list[str] | None) -> dict[str, str]:
    out = {}
    for it in items or []:
        k, sep, v = it.partition("=")
        if not sep or not k:
            raise PredictError(f"--param expects name=value, got {it!r}")
        out[k.strip()] = v.strip()
    return out


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("predict", help="judge a bag's scans offline, as the live node would",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bag", help="a .mcap file or a rosbag2 directory")
    p.add_argument("--out", required=True, metavar="OUT.mcap", help="output MCAP (must not exist)")
    p.add_argument("--model", default=None, metavar="DIR", help="model directory (default: the shipped model)")
    p.add_argument("--topic", action="append", help="PointCloud2 topic to judge (repeatable; default: all inputs)")
    p.add_argument("--param", action="append", metavar="NAME=VALUE", help="node parameter override (repeatable)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from .bag.reader import BagFormatError

    try:
        res = predict_bag(args.bag, args.out, model_dir=args.model, params=_parse_params(args.param),
                          topics=args.topic)
    except (PredictError, BagFormatError, OSError) as e:
        print(f"xmetro predict: error: {e}", file=sys.stderr)
        return 1
    print(res.summary())
    return 0
