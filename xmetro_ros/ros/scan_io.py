"""Scans ⇄ MCAP bags: what the simulator's campaign writes and the training tools read back.

Layout of a scan bag (rosbag2 format, see :mod:`xmetro_ros.bag`):

- ``/scanner_settings`` (xmetro_ros/msg/ScannerSettings, SI units) stamped 1 µs before each cloud;
- ``/scan`` (sensor_msgs/msg/PointCloud2, metres): float32 x, y, z, the scan's fields (length fields in metres,
  see ``ros.convert.LENGTH_FIELDS``) and, for simulated scans, the expected error as float32 ``ex, ey, ez``
  (metres; the training target nominal − measured, the simulator's truth: not a product output, and of the
  opposite sign to the node's ``dx, dy, dz``, see docs/conventions.md);
- one MCAP metadata record ``xmetro_scan/<i>`` per scan: key ``json`` = the scan's artifact dict, meta,
  original stamp, shape, field dtypes, settings (mm/ms), pose (mm) and scanner id — what the cloud cannot carry;
- one metadata record ``xmetro_manifest`` (key ``json``) holding the campaign manifest.

With ``exact=True`` an attachment ``xmetro_scan/<i>.npz`` adds the float64 points and expected error (mm) and the
fields at their original dtype, so that :func:`read_scans` returns the scans bit for bit. Without it (default:
files 2-3x smaller) points come back from float32 metres, i.e. to ~1e-5 mm, and the expected error to ~1e-7 mm.

Cloud stamps: scans whose ``stamp_ns`` are strictly increasing and positive keep them; otherwise (simulated scans
all stamped 0) scan i is stamped (i + 1) s, so that each cloud has its own settings message before it. The original
stamp comes back from the metadata record.
"""

from __future__ import annotations

import io
import itertools
import json
import logging
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ..bag import qos_profiles
from ..bag.reader import BagReader
from ..bag.writer import BagWriter
from ..scan.artifact_specs import artifact_from_dict
from ..scan.geometry import HeadPose
from ..scan.scan import Scan
from ..scan.scanner import ScannerModel, ScanSettings

__all__ = [
    "MANIFEST_RECORD",
    "SCAN_RECORD",
    "ScanBagError",
    "iter_scans",
    "read_manifest",
    "read_scans",
    "write_scans",
]

log = logging.getLogger(__name__)

MANIFEST_RECORD = "xmetro_manifest"
SCAN_RECORD = "xmetro_scan/"
_SETTINGS_LEAD_NS = 1000  # settings are stamped this long before their cloud
_ERROR_FIELDS = ("ex", "ey", "ez")


class ScanBagError(ValueError):
    """A bag that does not hold scans as expected (no cloud topic, inconsistent scan records...)."""


def _stamps(scans: list[Scan]) -> list[int]:
    s = [int(sc.stamp_ns) for sc in scans]
    if s and s[0] > _SETTINGS_LEAD_NS and all(b > a for a, b in itertools.pairwise(s)):
        return s
    return [(i + 1) * 1_000_000_000 for i in range(len(scans))]


def write_scans(
    path: str | Path,
    scans: Iterable[Scan],
    manifest: dict[str, Any] | None = None,
    topic: str = "/scan",
    settings_topic: str = "/scanner_settings",
    *,
    exact: bool = False,
    compression: str | None = "zstd",
) -> Path:
    """Write scans (each a PointCloud2 + the ScannerSettings it was taken with) to a bag; return its path.

    Args:
        path: ``*.mcap`` (one file) or a directory name (rosbag2 directory); must not exist.
        scans: the scans (consumed once; a generator keeps memory flat).
        manifest: JSON-serialisable campaign description stored as the ``xmetro_manifest`` metadata record.
        exact: also store float64 points / expected error / original-dtype fields (see module doc).
        compression: MCAP chunk compression (``"zstd"`` or None).

    Raises:
        ValueError: a scan field named x/y/z/ex/ey/ez; TypeError: manifest or meta not JSON-serialisable;
        BagWriteError: I/O error.
    """
    from .convert import scan_to_cloud, settings_to_msg

    scans = list(scans) if not isinstance(scans, list) else scans
    stamps = _stamps(scans)
    with BagWriter(path, compression=compression) as w:
        # The QoS a live scanner would offer (settings transient-local), so `ros2 bag play` re-offers it.
        w.add_topic(settings_topic, "xmetro_ros/msg/ScannerSettings", [qos_profiles.SETTINGS])
        w.add_topic(topic, "sensor_msgs/msg/PointCloud2", [qos_profiles.CLOUD])
        if manifest is not None:
            w.add_metadata(MANIFEST_RECORD, {"json": json.dumps(manifest)})
        for i, (scan, stamp) in enumerate(zip(scans, stamps, strict=True)):
            clash = set(scan.fields) & {"x", "y", "z", *_ERROR_FIELDS}
            if clash:
                raise ValueError(f"scan {i}: field names {sorted(clash)} are reserved")
            if scan.expected_error is not None:
                err = np.asarray(scan.expected_error)
                extra = {name: err[..., k] for k, name in enumerate(_ERROR_FIELDS)}
                wire = Scan(scan.points, scan.settings, scan.pose, scan.scanner_id, {**scan.fields, **extra},
                            scan.frame_id, scan.stamp_ns)
            else:
                wire = scan
            cloud = scan_to_cloud(wire, stamp)
            settings = settings_to_msg(scan.settings, scan.pose, scan.frame_id, stamp - _SETTINGS_LEAD_NS,
                                       scan.scanner_id)
            record = {
                "index": i,
                "stamp_ns": int(scan.stamp_ns),
                "header_stamp_ns": int(stamp),
                "shape": list(scan.shape),
                "organized": scan.organized,
                "fields": {k: str(np.asarray(v).dtype) for k, v in scan.fields.items()},
                "has_expected_error": scan.expected_error is not None,
                "artifact": scan.artifact.to_dict() if scan.artifact is not None else None,
                "meta": scan.meta,
                "scanner_id": scan.scanner_id,
                "frame_id": scan.frame_id,
                "settings": {"lateral_density": scan.settings.lateral_density,
                             "direction_density": scan.settings.direction_density,
                             "exposure_ms": scan.settings.exposure_ms},
                "pose": {"position": scan.pose.position.tolist(), "rotation": scan.pose.rotation.tolist()},
                "exact": bool(exact),
            }
            w.add_metadata(f"{SCAN_RECORD}{i}", {"json": json.dumps(record)})
            if exact:
                buf = io.BytesIO()
                arrays: dict[str, Any] = {"points": np.asarray(scan.points, dtype=np.float64)}
                if scan.expected_error is not None:
                    arrays["expected_error"] = np.asarray(scan.expected_error, dtype=np.float64)
                arrays.update({f"field_{k}": np.asarray(v) for k, v in scan.fields.items()})
                np.savez(buf, **arrays)
                w.add_attachment(f"{SCAN_RECORD}{i}.npz", buf.getvalue(), "application/x-npz", stamp)
            w.write(settings_topic, settings, stamp - _SETTINGS_LEAD_NS)
            w.write(topic, cloud, stamp)
    return Path(path)


def read_manifest(path: str | Path) -> dict[str, Any] | None:
    """The ``xmetro_manifest`` of a scan bag, or None when it has none."""
    r = BagReader(path)
    for _ in r.messages(deserialize=False):
        pass
    rec = r.metadata.get(MANIFEST_RECORD)
    return json.loads(rec["json"]) if rec else None


def _scan_from_record(cloud: Any, rec: dict[str, Any], attachment: bytes | None) -> Scan:
    from .convert import cloud_to_scan

    shape = tuple(rec["shape"])
    settings = ScanSettings(**rec["settings"])
    pose = HeadPose(np.asarray(rec["pose"]["position"]), np.asarray(rec["pose"]["rotation"]))
    artifact = artifact_from_dict(rec["artifact"]) if rec.get("artifact") else None
    names = list(rec["fields"])
    if rec.get("has_expected_error"):
        names += list(_ERROR_FIELDS)
    s = cloud_to_scan(cloud, settings, pose, rec["scanner_id"], extra_fields=names)
    points = s.points.reshape(*shape, 3)
    fields = {k: np.asarray(s.fields[k]).reshape(shape).astype(rec["fields"][k]) for k in rec["fields"]}
    expected = None
    if rec.get("has_expected_error"):
        expected = np.stack([np.asarray(s.fields[k], dtype=np.float64).reshape(shape) for k in _ERROR_FIELDS],
                            axis=-1)
    if attachment is not None:
        with np.load(io.BytesIO(attachment)) as z:
            points = z["points"]
            if "expected_error" in z:
                expected = z["expected_error"]
            fields = {k: z[f"field_{k}"] for k in rec["fields"]}
    return Scan(points=points, settings=settings, pose=pose, scanner_id=rec["scanner_id"], fields=fields,
                frame_id=rec["frame_id"], stamp_ns=int(rec["stamp_ns"]), artifact=artifact,
                expected_error=expected, meta=rec.get("meta") or {})


def iter_scans(path: str | Path, topic: str = "/scan", settings_topic: str = "/scanner_settings",
               scanner: ScannerModel | None = None) -> Iterator[Scan]:
    """Yield the scans of a bag in order.

    Scans written by :func:`write_scans` come back with artifact, expected error, meta and original stamps.
    Clouds recorded elsewhere are paired with the latest ScannerSettings stamped at or before them; without one,
    the scanner's default settings and the looking-down pose are used and ``meta["settings_defaulted"]`` is True.

    Raises:
        ScanBagError: the bag has no ``topic``. FileNotFoundError / BagFormatError: see BagReader.
    """
    from .convert import cloud_to_scan, settings_from_msg, stamp_to_ns

    r = BagReader(path)
    topics = r.topics()
    if topic not in topics:
        raise ScanBagError(f"bag {path} has no topic {topic} (topics: {sorted(topics)})")
    settings: list[tuple[int, Any]] = []
    records: dict[int, dict[str, Any]] = {}  # header stamp → scan record
    parsed: set[str] = set()
    deferred: list[Any] = []

    def scan_records() -> dict[int, dict[str, Any]]:
        for name in [n for n in r.metadata if n.startswith(SCAN_RECORD) and n not in parsed]:
            parsed.add(name)
            rec = json.loads(r.metadata[name]["json"])
            records[int(rec["header_stamp_ns"])] = rec
        return records

    def convert(cloud: Any) -> Scan:
        stamp = stamp_to_ns(cloud.header.stamp)
        rec = scan_records().get(stamp)
        if rec is not None:
            return _scan_from_record(cloud, rec, r.attachments.get(f"{SCAN_RECORD}{rec['index']}.npz"))
        before = [m for t, m in settings if t <= stamp]
        if before:
            st, pose, scanner_id, _frame, _t = settings_from_msg(before[-1])
            return cloud_to_scan(cloud, st, pose, scanner_id, meta={"settings_defaulted": False})
        model = scanner or ScannerModel.load()
        return cloud_to_scan(cloud, model.default_settings, HeadPose.looking_down(model.standoff_mm), model.id,
                             meta={"settings_defaulted": True})

    for m in r.messages([topic, settings_topic]):
        if m.topic == settings_topic:
            settings.append((stamp_to_ns(m.msg.header.stamp), m.msg))
            continue
        stamp = stamp_to_ns(m.msg.header.stamp)
        if stamp in scan_records() or not records:
            yield convert(m.msg)
        else:
            deferred.append(m.msg)  # its record comes later in the file
    for cloud in deferred:
        yield convert(cloud)


def read_scans(path: str | Path, topic: str = "/scan", settings_topic: str = "/scanner_settings",
               scanner: ScannerModel | None = None) -> list[Scan]:
    """All scans of a bag (see :func:`iter_scans`)."""
    return list(iter_scans(path, topic, settings_topic, scanner))
