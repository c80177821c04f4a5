"""An assembled scan of profiles (:class:`~xmetro_ros.scan.assembly.AssembledScan`) → what the node judges: an
organized ``PointCloud2`` in the fixed frame (the scan's outputs are published on it), each row's head pose, and
the settings it was taken with, with where each setting came from. Also what a dropped profile is reported as.

Settings of an assembled scan (docs/profile-streams.md, "Settings"), per setting, the first that has it:

1. a valid ``ScannerSettings`` on the ``scanner_settings`` topic stamped at or before the scan: all three from it
   (its ``head_pose`` is not used: the poses come from tf);
2. the driver's own parameters (``driver_node`` + ``driver_mapping``): the exposure, and the lateral density
   where the driver exposes a resolution;
3. measured from the scan itself (:func:`~xmetro_ros.scan.assembly.measured_densities`): the direction density
   from the motion between profiles, the lateral density from the points' spacing along the line;
4. the node's ``default_*`` parameters: then ``settings_defaulted`` is true and the message says which.

No DDS: messages are built, never sent.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from sensor_msgs.msg import PointCloud2

from ..msg import ScannerSettings
from ..scan.assembly import AssembledScan, DropReason, measured_densities
from ..scan.geometry import RowPoses
from ..scan.scanner import ScannerModel, ScanSettings
from .convert import scan_to_cloud, settings_to_msg

__all__ = ["DROP_ERRORS", "PosedScan", "assembled_input", "choose_settings", "drop_message"]

#: ScanQuality error code name and the account given to the user of each drop reason (IDLE is not an error: the
#: profiles between scans).
DROP_ERRORS: dict[DropReason, tuple[str, str]] = {
    DropReason.TF_MISSING: ("TF_MISSING", "the fixed or the sensor frame never appeared on /tf or /tf_static within "
                            "tf_timeout: is the robot's state publisher running, and the hand-eye transform on "
                            "/tf_static?"),
    DropReason.TF_NOT_CONNECTED: ("TF_NOT_CONNECTED", "both frames are known but no chain of transforms joins them: "
                                  "a missing link between the robot and the sensor, or the wrong fixed_frame"),
    DropReason.TF_LATE: ("TF_LATE", "the tf never reached the profile's stamp within tf_timeout: tf published late "
                         "or too slowly, or the clocks of the driver and the robot differ"),
    DropReason.QUEUE_FULL: ("TF_LATE", "too many profiles were waiting for their tf (held queue full): tf stopped or "
                            "lags far behind the profiles"),
    DropReason.TF_PAST: ("TF_EXTRAPOLATION", "the profile is older than the tf history (tf_cache_time), or its pose "
                         "would need extrapolation beyond tf_max_extrapolation: it is never judged with a guess"),
    DropReason.OUT_OF_ORDER: ("PROFILE_OUT_OF_ORDER", "its stamp is not newer than the previous profile's (a driver "
                              "restarted, two drivers on one topic, or a replay looping)"),
    DropReason.BAD_PROFILE: ("BAD_LAYOUT", "the profile's points are not (W, 3) or a field does not match them"),
    DropReason.SHORT_SCAN: ("SHORT_SCAN", "its scan had fewer than min_scan_rows profiles"),
}


@dataclass
class PosedScan:
    """The per-scan inputs the organized cloud of an assembled scan does not carry.

    Attributes:
        row_poses: each row's head pose, mm, fixed frame.
        settings: the settings it is judged with; ``settings_msg`` the same as a message (``head_pose`` = the
            first row's head pose, frame = the fixed frame).
        defaulted: a setting came from the node's defaults.
        note: where each setting came from, and how the scan was assembled (appended to ScanQuality.message).
        profiles: the scan's own rows (profiles), context rows not counted.
        rows: (start, stop) of the rows to publish when the others are context (a chunk of a stream judged with
            its neighbours' rows); None = all.
        stamp_ns: the stamp of the outputs: the first published row's.
    """

    row_poses: RowPoses
    settings: ScanSettings
    settings_msg: ScannerSettings
    defaulted: bool
    note: str
    profiles: int
    rows: tuple[int, int] | None = None
    stamp_ns: int = 0


def choose_settings(scan: AssembledScan, topic: ScanSettings | None, driver: Mapping[str, float] | None,
                    defaults: ScanSettings, scanner: ScannerModel) -> tuple[ScanSettings, bool, str]:
    """(settings, defaulted, where each came from) by the order of the module doc. ``topic``: the valid
    ScannerSettings values for the scan's stamp, or None; ``driver``: values from the driver's parameters, keys
    ``exposure_ms`` and ``lateral_density`` (per mm), either may be absent."""
    if topic is not None:
        return topic, False, "settings from scanner_settings"
    lateral, direction = measured_densities(scan, scanner.standoff_mm)
    driver = driver or {}
    values: dict[str, float] = {}
    source: dict[str, str] = {}
    for name, measured in (("lateral_density", lateral), ("direction_density", direction),
                           ("exposure_ms", None)):
        if driver.get(name) is not None:
            values[name], source[name] = float(driver[name]), "driver"
        elif measured is not None:
            values[name], source[name] = float(measured), "measured"
        else:
            values[name], source[name] = float(getattr(defaults, name)), "defaulted"
    settings = ScanSettings(values["lateral_density"], values["direction_density"], values["exposure_ms"])
    by: dict[str, list[str]] = {}
    for name, src in source.items():
        by.setdefault(src, []).append(name.replace("_ms", ""))
    note = "settings: " + "; ".join(f"{', '.join(names)} {src}" for src, names in by.items())
    return settings, "defaulted" in by, note


def assembled_input(scan: AssembledScan, settings: ScanSettings, defaulted: bool, note: str,
                    scanner_id: str) -> tuple[PointCloud2, PosedScan]:
    """The organized cloud (float32 x, y, z metres in the fixed frame, NaN for no return, the profiles' extra fields
    as float32; stamped with the first profile's stamp) and the :class:`PosedScan` of ``scan``."""
    core_scan = scan.to_scan(settings, scanner_id)
    rp = core_scan.row_poses
    assert rp is not None  # to_scan always sets them
    msg = scan_to_cloud(core_scan)
    settings_msg = settings_to_msg(settings, core_scan.pose, scan.frame_id, int(scan.stamps_ns[0]), scanner_id)
    a, b = scan.core_rows if scan.core_rows is not None else (0, scan.shape[0])
    span = (int(scan.stamps_ns[b - 1]) - int(scan.stamps_ns[a])) / 1e9
    context = (f" (judged with {a} + {scan.shape[0] - b} context rows of the chunks before and after)"
               if scan.core_rows is not None else "")
    full = (f"assembled from {b - a} profiles over {span:.3f} s (end {scan.end.value}){context}, each judged from "
            f"its own sensor pose; {note}")
    return msg, PosedScan(rp, settings, settings_msg, defaulted, full, b - a, scan.core_rows,
                          int(scan.stamps_ns[a]))


def drop_message(reason: DropReason, count: int, detail: str) -> tuple[str, str]:
    """(ScanQuality error code name, message) for ``count`` profiles dropped for ``reason`` (not IDLE)."""
    code, why = DROP_ERRORS[reason]
    last = f" (latest: {detail})" if detail else ""
    return code, f"{count} profile(s) dropped, {reason.value}: {why}{last}"
