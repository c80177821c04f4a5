"""Profile assembly (ROS-free): a stream of single laser-line profiles + the sensor pose of each → organized scans
in a fixed frame, one row per profile, each row with its own sensor pose and stamp (docs/profile-streams.md).

Input (what a line-scanner driver publishes, one ``PointCloud2`` per profile): a :class:`Profile` = stamp (ns),
``frame_id`` (the sensor frame), points (W, 3) in the **sensor frame, metres** (x along the laser line, z the range,
y ≈ 0; +inf or NaN in any coordinate = no return), optional per-point fields (W,). The pose of each profile is
``T(fixed_frame ← sensor frame)`` at its stamp from a :class:`~xmetro_ros.scan.tf_buffer.TransformBuffer` (fed from
/tf and /tf_static), never guessed.

Output: an :class:`AssembledScan`: points (H, W, 3) in the **fixed frame, millimetres** (the core's unit), NaN where
a profile had no return or was narrower than W (rows keep their width; nothing is compacted), per-row sensor poses
(H, 4, 4, translation mm), per-row stamps, per-row head poses in our head frame (:data:`HEAD_IN_SENSOR`).

Order and holding: profiles must come with increasing stamps (else ``OUT_OF_ORDER``). A profile whose pose cannot
be had yet (frame unknown, not connected, or the tf not yet arrived: a retryable
:class:`~xmetro_ros.scan.tf_buffer.TfErrorCode`) is held, in a bounded FIFO, until the tf arrives (call
:meth:`ProfileAssembler.poll` after feeding the buffer) or until it is ``tf_timeout_s`` older than the clock (the
newest profile's stamp, or the ``now_ns`` given to :meth:`~ProfileAssembler.poll`); then it is dropped and counted
with its reason. Profiles are resolved strictly in stamp order: one held profile holds the ones behind it.

Scan boundaries (:class:`ScanTrigger`), per ``kind``:

- ``count``: a scan is ``count`` profiles.
- ``window``: a scan holds the profiles within ``window_s`` of its first one; the first profile at or past the
  window starts the next scan.
- ``gap``: a scan ends at a pause in the stream longer than ``gap_s`` or when the sensor's speed (its origin's
  displacement between consecutive profiles over their time difference, translation only) falls below
  ``min_speed_m_s``; profiles taken while stopped belong to no scan (``IDLE``).
- ``signal``: :meth:`ProfileAssembler.start` / :meth:`~ProfileAssembler.stop`, each at a stamp (default: just after
  the newest profile received): profiles stamped in [start, stop) form the scan, others are ``IDLE``.

``gap_s`` and ``min_speed_m_s`` also guard the other kinds (a scan cut by a pause ends with ``GAP``, by a stop with
``STOPPED``); ``max_rows`` caps every scan (``MAX_ROWS``); :meth:`~ProfileAssembler.flush` closes the open one
(``FLUSH``). A scan of fewer than ``min_rows`` rows is not emitted (its rows are dropped as ``SHORT_SCAN``). The
first profile after the start or a pause has no speed: it joins the scan only when the next one shows motion.

Accounting (:class:`AssemblerCounters`): received = assembled + Σ dropped[reason] + pending + in progress, always.
"""

from __future__ import annotations

import enum
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from .geometry import HeadPose, RowPoses
from .scan import Scan
from .scanner import ScanSettings
from .tf_buffer import TfErrorCode, TransformBuffer, TransformError

__all__ = [
    "HEAD_IN_SENSOR",
    "AssembledScan",
    "AssemblerCounters",
    "DropReason",
    "DroppedProfile",
    "Profile",
    "ProfileAssembler",
    "ScanEnd",
    "ScanTrigger",
    "head_poses_from_sensor",
    "measured_densities",
]

# R(sensor ← head): the columns are the head's X, Y, Z axes in the sensor frame. The sensor frame of a line-scanner
# driver has x along the laser line and z along the range (the laser points along sensor +z); our head frame has the
# line along head +X and the laser along head −Z (docs/conventions.md). So head X = sensor x, head Z = −sensor z and
# (right-handed) head Y = −sensor y: a half turn about x. The head origin is the sensor frame's origin.
HEAD_IN_SENSOR = np.diag([1.0, -1.0, -1.0])
HEAD_IN_SENSOR.setflags(write=False)


class DropReason(str, enum.Enum):
    """Why a profile was not assembled into a scan."""

    OUT_OF_ORDER = "OUT_OF_ORDER"  # stamp not newer than the previous profile's
    BAD_PROFILE = "BAD_PROFILE"  # points not (W, 3), or a field not (W,)
    TF_MISSING = "TF_MISSING"  # held until the timeout: the fixed or sensor frame never appeared in tf
    TF_NOT_CONNECTED = "TF_NOT_CONNECTED"  # held until the timeout: both frames known, no path between them
    TF_LATE = "TF_LATE"  # held until the timeout: the tf never reached the profile's stamp
    TF_PAST = "TF_PAST"  # older than the tf history (beyond the extrapolation bound): dropped at once
    QUEUE_FULL = "QUEUE_FULL"  # the oldest held profile, pushed out by a new one (max_pending)
    IDLE = "IDLE"  # resolved but in no scan: before start / after stop, or while the sensor stood still
    SHORT_SCAN = "SHORT_SCAN"  # in a scan that ended with fewer than min_rows rows


class ScanEnd(str, enum.Enum):
    """What ended an :class:`AssembledScan`."""

    COUNT = "COUNT"
    WINDOW = "WINDOW"
    GAP = "GAP"  # a pause in the stream longer than gap_s
    STOPPED = "STOPPED"  # the sensor's speed fell below min_speed_m_s
    SIGNAL = "SIGNAL"  # stop() (or start() while recording)
    MAX_ROWS = "MAX_ROWS"
    FLUSH = "FLUSH"


_TF_DROP = {TfErrorCode.UNKNOWN_FRAME: DropReason.TF_MISSING, TfErrorCode.NOT_CONNECTED: DropReason.TF_NOT_CONNECTED,
            TfErrorCode.EXTRAPOLATION_FUTURE: DropReason.TF_LATE, TfErrorCode.EXTRAPOLATION_PAST: DropReason.TF_PAST}


@dataclass
class Profile:
    """One laser-line profile as the driver publishes it.

    Attributes:
        stamp_ns: acquisition time, ns (``header.stamp``).
        frame_id: the sensor frame (``header.frame_id``).
        points: (W, 3) float, sensor frame, metres; a non-finite coordinate (+inf, NaN) = no return.
        fields: extra per-point fields, name → (W,) array (intensity, ...).
    """

    stamp_ns: int
    frame_id: str
    points: np.ndarray
    fields: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass(frozen=True)
class ScanTrigger:
    """Where scans start and end (see the module doc).

    Attributes:
        kind: ``count`` | ``window`` | ``gap`` | ``signal``.
        count: profiles per scan (``count``).
        window_s: scan duration, seconds (``window``).
        gap_s: a pause between consecutive profiles longer than this ends the scan, seconds (``gap``; a guard for
            the others).
        min_speed_m_s: the sensor origin moving slower than this ends the scan and makes profiles ``IDLE``, m/s
            (``gap``; a guard for the others).
    """

    kind: Literal["count", "window", "gap", "signal"]
    count: int | None = None
    window_s: float | None = None
    gap_s: float | None = None
    min_speed_m_s: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in ("count", "window", "gap", "signal"):
            raise ValueError(f"unknown trigger kind {self.kind!r} (count, window, gap, signal)")
        if self.kind == "count" and not (self.count is not None and self.count >= 1):
            raise ValueError("a count trigger needs count >= 1")
        if self.kind == "window" and not (self.window_s is not None and self.window_s > 0):
            raise ValueError("a window trigger needs window_s > 0")
        if self.kind == "gap" and self.gap_s is None and self.min_speed_m_s is None:
            raise ValueError("a gap trigger needs gap_s or min_speed_m_s")
        if self.gap_s is not None and not self.gap_s > 0:
            raise ValueError("gap_s must be > 0")
        if self.min_speed_m_s is not None and not self.min_speed_m_s > 0:
            raise ValueError("min_speed_m_s must be > 0")


@dataclass
class AssemblerCounters:
    """Profile accounting of a :class:`ProfileAssembler` (a copy rides on each scan).

    Attributes:
        received: profiles given to :meth:`ProfileAssembler.add`.
        assembled: profiles in emitted scans.
        scans: scans emitted.
        pending: profiles held, waiting for their tf.
        in_progress: profiles in the scan being built (and a lead profile waiting to show motion).
        gaps: pauses longer than ``gap_s`` seen in the stream.
        dropped: profiles dropped, by reason.
    """

    received: int = 0
    assembled: int = 0
    scans: int = 0
    pending: int = 0
    in_progress: int = 0
    gaps: int = 0
    dropped: dict[DropReason, int] = field(default_factory=lambda: dict.fromkeys(DropReason, 0))

    def copy(self) -> AssemblerCounters:
        """An independent copy."""
        return AssemblerCounters(self.received, self.assembled, self.scans, self.pending, self.in_progress,
                                 self.gaps, dict(self.dropped))

    @property
    def balanced(self) -> bool:
        """received = assembled + Σ dropped + pending + in progress."""
        return self.received == self.assembled + sum(self.dropped.values()) + self.pending + self.in_progress


@dataclass(frozen=True)
class DroppedProfile:
    """A dropped profile, for reports (the assembler keeps the last few)."""

    stamp_ns: int
    frame_id: str
    reason: DropReason
    detail: str = ""


def head_poses_from_sensor(sensor_poses: np.ndarray,
                           head_in_sensor: np.ndarray = HEAD_IN_SENSOR) -> tuple[np.ndarray, np.ndarray]:
    """Per-row head positions (H, 3) and rotations (H, 3, 3) from sensor poses (H, 4, 4).

    The head origin is the sensor origin; ``rotation = R(fixed ← sensor) · head_in_sensor`` (columns = head axes in
    the fixed frame, as :class:`~xmetro_ros.scan.geometry.HeadPose` wants). Units follow the input translation.
    """
    p = np.asarray(sensor_poses, dtype=float)
    return p[:, :3, 3].copy(), p[:, :3, :3] @ np.asarray(head_in_sensor, dtype=float)


@dataclass
class AssembledScan:
    """An organized scan assembled from profiles (rows = profiles, in stamp order).

    Attributes:
        points: (H, W, 3) float64, fixed frame, mm; NaN where there was no return or the row was narrower.
        valid: (H, W) bool, the finite points.
        widths: (H,) int, each profile's own width (W = max).
        stamps_ns: (H,) int64, each row's stamp.
        sensor_poses: (H, 4, 4) ``T(fixed ← sensor)`` of each row, translation in mm.
        fields: extra per-point fields stacked (H, W): NaN padding for float fields, 0 for integer ones (as
            float64 when a field is missing from some rows).
        frame_id: the fixed frame. sensor_frame: the frame the poses were looked up for.
        end: what ended the scan. index: its number (0, 1, ...) in this assembler.
        counters: a copy of the assembler's counters when it was emitted.
        core_rows: (start, stop): the rows that are this scan's own when the others are context borrowed from the
            chunks before and after it (a profile stream judged chunk by chunk); None = all rows are its own.
    """

    points: np.ndarray
    valid: np.ndarray
    widths: np.ndarray
    stamps_ns: np.ndarray
    sensor_poses: np.ndarray
    fields: dict[str, np.ndarray]
    frame_id: str
    sensor_frame: str
    end: ScanEnd
    index: int
    counters: AssemblerCounters
    core_rows: tuple[int, int] | None = None

    @property
    def own_rows(self) -> int:
        """How many rows are this scan's own (not context)."""
        return self.shape[0] if self.core_rows is None else self.core_rows[1] - self.core_rows[0]

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W)."""
        return int(self.points.shape[0]), int(self.points.shape[1])

    def rows(self, start: int, stop: int) -> AssembledScan:
        """Rows ``start:stop`` as a scan of their own (views where numpy gives them)."""
        sl = slice(start, stop)
        return replace(self, points=self.points[sl], valid=self.valid[sl], widths=self.widths[sl],
                       stamps_ns=self.stamps_ns[sl], sensor_poses=self.sensor_poses[sl],
                       fields={k: v[sl] for k, v in self.fields.items()}, core_rows=None)

    @staticmethod
    def concat(parts: list[AssembledScan]) -> AssembledScan:
        """Consecutive scans' rows as one (the last part's end, index and counters; NaN / 0 padding to the widest;
        a field missing from a part is NaN there)."""
        if len(parts) == 1:
            return parts[0]
        w = max(p.shape[1] for p in parts)

        def pad(a: np.ndarray, fill: float) -> np.ndarray:
            if a.shape[1] == w:
                return a
            out = np.full((a.shape[0], w, *a.shape[2:]), fill, dtype=a.dtype)
            out[:, : a.shape[1]] = a
            return out

        names = sorted({k for p in parts for k in p.fields})
        fields = {}
        for k in names:
            arrs = [p.fields.get(k) for p in parts]
            dt = np.result_type(*[a.dtype for a in arrs if a is not None])
            if any(a is None for a in arrs) and dt.kind != "f":
                dt = np.dtype(np.float64)
            fill = np.nan if dt.kind == "f" else 0
            fields[k] = np.concatenate([pad(np.full(p.shape, np.nan) if a is None else a.astype(dt, copy=False), fill)
                                        for p, a in zip(parts, arrs, strict=True)])
        last = parts[-1]
        return replace(last, points=np.concatenate([pad(p.points, np.nan) for p in parts]),
                       valid=np.concatenate([pad(p.valid, False) for p in parts]),
                       widths=np.concatenate([p.widths for p in parts]),
                       stamps_ns=np.concatenate([p.stamps_ns for p in parts]),
                       sensor_poses=np.concatenate([p.sensor_poses for p in parts]), fields=fields, core_rows=None)

    def head_arrays(self, head_in_sensor: np.ndarray = HEAD_IN_SENSOR) -> tuple[np.ndarray, np.ndarray]:
        """Per-row head positions (H, 3) mm and rotations (H, 3, 3), fixed frame (:func:`head_poses_from_sensor`)."""
        return head_poses_from_sensor(self.sensor_poses, head_in_sensor)

    def head_poses(self, head_in_sensor: np.ndarray = HEAD_IN_SENSOR) -> list[HeadPose]:
        """One :class:`~xmetro_ros.scan.geometry.HeadPose` per row (position mm, fixed frame)."""
        pos, rot = self.head_arrays(head_in_sensor)
        return [HeadPose(pos[i], rot[i]) for i in range(pos.shape[0])]


    def row_poses(self, head_in_sensor: np.ndarray = HEAD_IN_SENSOR) -> RowPoses:
        """The per-row head poses as the core's :class:`~xmetro_ros.scan.geometry.RowPoses` (mm, fixed frame)."""
        pos, rot = self.head_arrays(head_in_sensor)
        return RowPoses.per_row(pos, rot, self.shape[1])

    def to_scan(self, settings: ScanSettings, scanner_id: str,
                head_in_sensor: np.ndarray = HEAD_IN_SENSOR) -> Scan:
        """The scan the judge takes: points (H, W, 3) mm in the fixed frame, each row judged from its own head pose
        (``row_poses``; ``pose`` = the first row's), stamped with the first profile's stamp, the extra fields kept."""
        rp = self.row_poses(head_in_sensor)
        return Scan(points=self.points, settings=settings, pose=rp.first(), scanner_id=scanner_id,
                    fields=dict(self.fields), frame_id=self.frame_id, stamp_ns=int(self.stamps_ns[0]),
                    row_poses=rp, meta={"assembled": {"index": self.index, "end": self.end.value,
                                                      "sensor_frame": self.sensor_frame}})


def measured_densities(scan: AssembledScan, standoff_mm: float) -> tuple[float | None, float | None]:
    """(lateral, direction) densities, per mm, measured from an assembled scan; None where it cannot tell.

    Lateral: the spacing of the points along each profile, taken at the reference stand-off (``u = standoff ·
    x / z`` in the sensor frame: what the settings' lateral density means), as the common slope of u against the
    point's index in its profile (so it needs the index kept: no-returns as NaN, not dropped). Direction: the
    median distance between consecutive profiles' sensor origins (the motion), inverted. Both are what the scanner
    really did; a driver parameter or a ScannerSettings message may say otherwise (docs/profile-streams.md says
    which wins). On the virtual scanner the lateral density reads 0.1-0.2 % low (its noise is not along the ray).
    """
    h, w = scan.shape
    direction = None
    if h >= 2:
        step = np.linalg.norm(np.diff(scan.sensor_poses[:, :3, 3], axis=0), axis=1)
        step = step[step > 0]
        if step.size:
            direction = 1.0 / float(np.median(step))
    lateral = None
    if w >= 2:
        # back to each row's sensor frame: p_s = R^T (p - t)
        rot, trans = scan.sensor_poses[:, :3, :3], scan.sensor_poses[:, :3, 3]
        d = scan.points - trans[:, None, :]
        xs = np.einsum("hwi,hi->hw", d, rot[:, :, 0])
        zs = np.einsum("hwi,hi->hw", d, rot[:, :, 2])
        with np.errstate(invalid="ignore", divide="ignore"):
            u = standoff_mm * xs / zs
        ok = scan.valid & np.isfinite(u) & (zs > 0)
        r_i, c_i = np.nonzero(ok)
        if r_i.size >= 3:
            # One line u = a_row + spacing · column per profile, a common slope (least squares with a per-row
            # intercept): the noise along the range averages out, where a median of neighbour differences is biased.
            uu, jj = u[r_i, c_i], c_i.astype(np.float64)
            n = np.bincount(r_i, minlength=h).astype(np.float64)
            nz = np.maximum(n, 1.0)
            dj = jj - (np.bincount(r_i, jj, minlength=h) / nz)[r_i]
            du = uu - (np.bincount(r_i, uu, minlength=h) / nz)[r_i]
            sxx = float(dj @ dj)
            if sxx > 0:
                spacing = abs(float(dj @ du) / sxx)
                if spacing > 0:
                    lateral = 1.0 / spacing
    return lateral, direction


@dataclass
class _Row:
    stamp_ns: int
    frame_id: str
    points: np.ndarray
    fields: dict[str, np.ndarray]
    pose: np.ndarray | None = None  # T(fixed ← sensor), metres, once resolved


class ProfileAssembler:
    """Profiles + a transform buffer → :class:`AssembledScan` s (see the module doc).

    Args:
        tf: the buffer the poses come from (fed by the caller from /tf and /tf_static).
        fixed_frame: the frame of the scans (e.g. the robot base or the part's fixture).
        trigger: the scan boundaries.
        sensor_frame: the frame to look up for every profile; None = each profile's ``frame_id``.
        tf_timeout_s: how long (stream time) a profile is held waiting for its tf, seconds.
        max_pending: most profiles held at once; a further one pushes the oldest out (``QUEUE_FULL``).
        max_rows: most rows in one scan (``MAX_ROWS`` ends it).
        min_rows: fewer rows than this and a scan is not emitted (``SHORT_SCAN``).
        keep_drops: how many recent drops :attr:`recent_drops` keeps.
        columns: where a profile's points go in their row: ``index`` (point i in column i: drivers that keep every
            position of the line, no-returns as +inf or NaN) or ``ray`` (drivers that drop no-returns, so a point's
            index no longer says which of the sensor's rays measured it: :func:`_columns_by_ray` puts it back).

    Not thread-safe (one caller feeds it; the buffer itself may be fed from another thread). The profiles' point
    and field arrays are kept by reference until their scan is built: do not reuse them.
    """

    def __init__(self, tf: TransformBuffer, fixed_frame: str, trigger: ScanTrigger, sensor_frame: str | None = None,
                 tf_timeout_s: float = 0.5, max_pending: int = 1000, max_rows: int = 100_000, min_rows: int = 1,
                 keep_drops: int = 64, columns: Literal["index", "ray"] = "index") -> None:
        if columns not in ("index", "ray"):
            raise ValueError(f"columns must be 'index' or 'ray', got {columns!r}")
        if not fixed_frame:
            raise ValueError("fixed_frame must be named")
        if not tf_timeout_s >= 0 or max_pending < 1 or max_rows < 1 or min_rows < 1:
            raise ValueError("tf_timeout_s >= 0, max_pending >= 1, max_rows >= 1 and min_rows >= 1 are required")
        self.tf = tf
        self.fixed_frame = fixed_frame
        self.trigger = trigger
        self.sensor_frame = sensor_frame
        self.tf_timeout_ns = round(tf_timeout_s * 1e9)
        self.max_pending = max_pending
        self.max_rows = max_rows
        self.min_rows = min_rows
        self.columns = columns
        self.counters = AssemblerCounters()
        self.recent_drops: deque[DroppedProfile] = deque(maxlen=keep_drops)
        self._pending: deque[_Row] = deque()
        self._rows: list[_Row] = []  # the scan being built
        self._lead: _Row | None = None  # first profile after a start / pause, waiting to show motion
        self._prev: _Row | None = None  # the previous resolved profile (speed, pauses)
        self._last_stamp: int | None = None  # newest accepted stamp
        self._clock = np.iinfo(np.int64).min
        self._events: list[tuple[int, str]] = []  # (stamp, "start" | "stop"), sorted
        self._recording = trigger.kind != "signal"
        self._out: list[AssembledScan] = []
        self._blocked: tuple[int, int] | None = None  # (tf version, head stamp) last seen waiting

    # -- input ---------------------------------------------------------------------------------------------------
    def add(self, profile: Profile) -> list[AssembledScan]:
        """Take one profile; returns the scans it completed (usually none)."""
        return self.add_many([profile])

    def add_many(self, profiles: list[Profile]) -> list[AssembledScan]:
        """Take profiles in arrival order and resolve their poses together (one tf lookup for the batch instead of
        one each: a 1 kHz stream fed every few milliseconds); returns the scans they completed. The same result as
        adding them one by one, except that a profile whose tf has not arrived yet waits with the ones behind it."""
        for profile in profiles:
            self._accept(profile)
        self._drain()
        while len(self._pending) > self.max_pending:
            old = self._pending.popleft()
            self._drop(old.stamp_ns, old.frame_id, DropReason.QUEUE_FULL, f"{self.max_pending} held")
            self._drain()
        return self._take()

    def _accept(self, profile: Profile) -> None:
        """Check one profile and hold it for its pose (or drop it, counted)."""
        self.counters.received += 1
        stamp = int(profile.stamp_ns)
        pts = np.asarray(profile.points)
        fields = {k: np.asarray(v) for k, v in profile.fields.items()}
        if pts.ndim != 2 or pts.shape[1] != 3 or any(
                v.shape != (pts.shape[0],) for v in fields.values()):
            self._drop(stamp, profile.frame_id, DropReason.BAD_PROFILE, f"points {pts.shape}")
            return
        if self._last_stamp is not None and stamp <= self._last_stamp:
            self._drop(stamp, profile.frame_id, DropReason.OUT_OF_ORDER, f"after {self._last_stamp} ns")
            return
        self._last_stamp = stamp
        self._clock = max(self._clock, stamp + 1)
        self._pending.append(_Row(stamp, profile.frame_id, pts, fields))

    def poll(self, now_ns: int | None = None) -> list[AssembledScan]:
        """Retry the held profiles (call after new tf arrived); ``now_ns`` (the caller's clock, ns) advances the
        timeouts, the signals and a ``gap_s`` / ``window_s`` end that no newer profile has shown yet."""
        if now_ns is not None:
            self._clock = max(self._clock, int(now_ns))
        self._drain()
        if not self._pending and self._rows:
            last, first = self._rows[-1].stamp_ns, self._rows[0].stamp_ns
            if self.trigger.gap_s is not None and self._clock - last > round(self.trigger.gap_s * 1e9):
                self.counters.gaps += 1
                self._close(ScanEnd.GAP)
                self._prev = None
            elif self.trigger.window_s is not None and self.trigger.kind == "window" \
                    and self._clock >= first + round(self.trigger.window_s * 1e9):
                self._close(ScanEnd.WINDOW)
        return self._take()

    def start(self, stamp_ns: int | None = None) -> list[AssembledScan]:
        """``signal`` trigger: profiles from ``stamp_ns`` on (default: after the newest received) form a scan."""
        return self._signal("start", stamp_ns)

    def stop(self, stamp_ns: int | None = None) -> list[AssembledScan]:
        """``signal`` trigger: the scan ends before ``stamp_ns`` (default: after the newest received); it is
        returned once every profile before that stamp is resolved or dropped."""
        return self._signal("stop", stamp_ns)

    def flush(self) -> list[AssembledScan]:
        """End of stream: held profiles that still cannot be resolved are dropped (their reason), every signal is
        applied, and the open scan is emitted (``FLUSH``)."""
        self._drain(final=True)
        for _, kind in self._events:
            self._apply(kind)
        self._events.clear()
        self._close(ScanEnd.FLUSH)
        self._drop_lead()
        return self._take()

    # -- internals -----------------------------------------------------------------------------------------------
    def _signal(self, kind: str, stamp_ns: int | None) -> list[AssembledScan]:
        if self.trigger.kind != "signal":
            raise ValueError(f"{kind}() needs a signal trigger, this one is {self.trigger.kind!r}")
        if stamp_ns is None:
            stamp_ns = np.iinfo(np.int64).min if self._last_stamp is None else self._last_stamp + 1
        self._events.append((int(stamp_ns), kind))
        self._events.sort(key=lambda e: e[0])
        self._drain()
        return self._take()

    def _apply_events(self, upto: int) -> None:
        while self._events and self._events[0][0] <= upto:
            self._apply(self._events.pop(0)[1])

    def _apply(self, kind: str) -> None:
        if self._recording:
            self._close(ScanEnd.SIGNAL)
            self._drop_lead()
        self._recording = kind == "start"

    def _drop(self, stamp: int, frame: str, reason: DropReason, detail: str = "") -> None:
        self.counters.dropped[reason] += 1
        self.recent_drops.append(DroppedProfile(stamp, frame, reason, detail))

    def _drop_lead(self) -> None:
        if self._lead is not None:
            self._drop(self._lead.stamp_ns, self._lead.frame_id, DropReason.IDLE, "no motion shown")
            self._lead = None

    def _take(self) -> list[AssembledScan]:
        out, self._out = self._out, []
        self.counters.pending = len(self._pending)
        self.counters.in_progress = len(self._rows) + (self._lead is not None)
        return out

    def _frame(self, row: _Row) -> str:
        return self.sensor_frame or row.frame_id

    def _status(self, rows: list[_Row]) -> tuple[np.ndarray, list[TfErrorCode]]:
        """Poses (n, 4, 4) and codes of ``rows``: one batch lookup per sensor frame."""
        poses = np.full((len(rows), 4, 4), np.nan)
        codes = [TfErrorCode.OK] * len(rows)
        frames: dict[str, list[int]] = {}
        for i, r in enumerate(rows):
            frames.setdefault(self._frame(r), []).append(i)
        for frame, idx in frames.items():
            try:
                res = self.tf.lookup_batch(self.fixed_frame, frame, [rows[i].stamp_ns for i in idx],
                                           raise_on_error=False)
            except TransformError as e:
                for i in idx:
                    codes[i] = e.code
                continue
            poses[idx] = res.matrices
            for i, c in zip(idx, res.codes(), strict=True):
                codes[i] = c
        return poses, codes

    def _drain(self, final: bool = False) -> None:
        """Resolve held profiles in stamp order while their poses can be had; drop the ones that never will."""
        while self._pending:
            head = self._pending[0]
            key = (self.tf.version, head.stamp_ns)
            if not final and key == self._blocked and self._clock - head.stamp_ns <= self.tf_timeout_ns:
                break  # the head waits for its tf and the buffer has not changed since: no lookup
            rows = list(self._pending)
            poses, codes = self._status(rows)
            blocked = False
            for i, (r, code) in enumerate(zip(rows, codes, strict=True)):
                if code is TfErrorCode.OK:
                    self._pending.popleft()
                    r.pose = poses[i]
                    self._resolved(r)
                elif code.retryable and not final and self._clock - r.stamp_ns <= self.tf_timeout_ns:
                    blocked = True
                    self._blocked = (self.tf.version, r.stamp_ns)
                    break
                else:
                    self._pending.popleft()
                    self._drop(r.stamp_ns, r.frame_id, _TF_DROP.get(code, DropReason.TF_MISSING),
                               f"{self.fixed_frame} ← {self._frame(r)}: {code.value}")
            if blocked or not self._pending:
                break
        # signals whose stamp no held profile precedes
        self._apply_events(self._pending[0].stamp_ns if self._pending else self._clock)

    def _resolved(self, r: _Row) -> None:
        """Place one resolved profile (pose known) into the scans."""
        self._apply_events(r.stamp_ns)
        trig = self.trigger
        prev, self._prev = self._prev, r
        if prev is not None and trig.gap_s is not None and r.stamp_ns - prev.stamp_ns > round(trig.gap_s * 1e9):
            self.counters.gaps += 1
            self._close(ScanEnd.GAP)
            self._drop_lead()
            prev = None
        if not self._recording:
            self._drop(r.stamp_ns, r.frame_id, DropReason.IDLE, "outside start / stop")
            return
        if trig.kind == "window" and self._rows and trig.window_s is not None \
                and r.stamp_ns - self._rows[0].stamp_ns >= round(trig.window_s * 1e9):
            self._close(ScanEnd.WINDOW)
        if trig.min_speed_m_s is not None:
            if prev is None:  # the stream's start or a pause (which closed the scan): no speed yet
                self._drop_lead()
                self._lead = r
                return
            assert prev.pose is not None and r.pose is not None
            dist = float(np.linalg.norm(r.pose[:3, 3] - prev.pose[:3, 3]))
            speed = dist / ((r.stamp_ns - prev.stamp_ns) * 1e-9)
            if speed < trig.min_speed_m_s:
                self._close(ScanEnd.STOPPED)
                self._drop_lead()
                self._drop(r.stamp_ns, r.frame_id, DropReason.IDLE, f"speed {speed:.3g} m/s")
                return
            if self._lead is not None:
                lead, self._lead = self._lead, None
                self._append(lead)
        self._append(r)

    def _append(self, r: _Row) -> None:
        self._rows.append(r)
        if self.trigger.kind == "count" and len(self._rows) >= (self.trigger.count or 0):
            self._close(ScanEnd.COUNT)
        elif len(self._rows) >= self.max_rows:
            self._close(ScanEnd.MAX_ROWS)

    def _close(self, end: ScanEnd) -> None:
        rows, self._rows = self._rows, []
        if not rows:
            return
        if len(rows) < self.min_rows:
            for r in rows:
                self._drop(r.stamp_ns, r.frame_id, DropReason.SHORT_SCAN, f"{len(rows)} < {self.min_rows} rows")
            return
        self.counters.assembled += len(rows)
        self.counters.scans += 1
        counters = self.counters.copy()
        counters.pending = len(self._pending)
        counters.in_progress = int(self._lead is not None)
        if self.columns == "ray":
            rows = _columns_by_ray(rows)
        self._out.append(_build(rows, self.fixed_frame, self._frame(rows[0]), end, self.counters.scans - 1,
                                counters))


def _columns_by_ray(rows: list[_Row]) -> list[_Row]:
    """Rows whose points sit in the column of the sensor's ray that measured them (``columns="ray"``).

    A laser line scanner's points lie on a fan of rays from its origin in the sensor's x-z plane, evenly spaced in
    ``tan θ = x / z`` (the virtual scanner's; a real sensor's columns are evenly spaced at its reference stand-off
    to a good approximation). The spacing is estimated over the whole scan (median of neighbouring points'
    differences, refined by least squares over all neighbours as whole multiples of it), then column =
    round(tan θ / spacing) − the scan's smallest. Dropped no-returns leave NaN columns, as an index-keeping driver's
    +inf would. Two points of a row in one column (noise of half a spacing): the first is kept, the other is no
    return. Extra fields follow their points.
    """
    tans, diffs = [], []
    for r in rows:
        p = np.asarray(r.points, dtype=np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            t = p[:, 0] / p[:, 2]
        t = np.where(np.isfinite(t) & (p[:, 2] > 0) & np.isfinite(p).all(axis=1), t, np.nan)
        tans.append(t)
        d = np.diff(t[np.isfinite(t)])
        diffs.append(np.abs(d[d != 0]))
    alld = np.concatenate(diffs) if diffs else np.zeros(0)
    if alld.size == 0:
        return rows
    step0 = float(np.median(alld))
    mult = np.maximum(np.round(alld / step0), 1.0)
    step = float(alld.sum() / mult.sum())
    cols = [np.round(t / step) for t in tans]
    finite = [c[np.isfinite(c)] for c in cols]
    lo = min((float(c.min()) for c in finite if c.size), default=0.0)
    hi = max((float(c.max()) for c in finite if c.size), default=0.0)
    width = int(hi - lo) + 1
    out = []
    for r, c in zip(rows, cols, strict=True):
        ok = np.isfinite(c)
        j = (c[ok] - lo).astype(np.int64)
        _, first = np.unique(j, return_index=True)  # one point a column
        src = np.flatnonzero(ok)[first]
        pts = np.full((width, 3), np.nan)
        pts[j[first]] = np.asarray(r.points, dtype=np.float64)[src]
        fields = {}
        for k, v in r.fields.items():
            v = np.asarray(v)
            arr = np.full(width, np.nan if v.dtype.kind == "f" else 0, dtype=v.dtype)
            arr[j[first]] = v[src]
            fields[k] = arr
        out.append(_Row(r.stamp_ns, r.frame_id, pts, fields, r.pose))
    return out


def _build(rows: list[_Row], fixed_frame: str, sensor_frame: str, end: ScanEnd, index: int,
           counters: AssemblerCounters) -> AssembledScan:
    """Stack the rows (NaN padding) and transform every point into the fixed frame at once (mm)."""
    h = len(rows)
    widths = np.array([r.points.shape[0] for r in rows], dtype=np.int64)
    w = int(widths.max())
    # planar (3, H, W): every operation below runs on contiguous (H, W) planes, no BLAS
    planes = np.full((3, h, w), np.nan)
    for i, r in enumerate(rows):
        planes[:, i, : widths[i]] = r.points.T
    valid = np.isfinite(planes[0]) & np.isfinite(planes[1]) & np.isfinite(planes[2])
    poses = np.stack([r.pose for r in rows if r.pose is not None])
    rot, trans_mm = poses[:, :3, :3] * 1000.0, poses[:, :3, 3] * 1000.0  # rot × 1000: metres in, mm out
    invalid = ~valid
    np.copyto(planes, 0.0, where=invalid)  # no inf arithmetic; these points become NaN below
    out = np.empty((h, w, 3))
    acc, tmp = np.empty((h, w)), np.empty((h, w))
    for i in range(3):  # p_fixed = R p_sensor + t
        np.multiply(planes[0], rot[:, i, 0, None], out=acc)
        acc += np.multiply(planes[1], rot[:, i, 1, None], out=tmp)
        acc += np.multiply(planes[2], rot[:, i, 2, None], out=tmp)
        acc += trans_mm[:, i, None]
        np.copyto(acc, np.nan, where=invalid)  # +inf or one NaN coordinate: the whole point is missing
        out[..., i] = acc
    poses_mm = poses.copy()
    poses_mm[:, :3, 3] = trans_mm
    fields: dict[str, np.ndarray] = {}
    for name in sorted({k for r in rows for k in r.fields}):
        present = [r.fields[name] for r in rows if name in r.fields]
        dtype = np.result_type(*present)
        fill: float = np.nan
        if not np.issubdtype(dtype, np.floating):
            if len(present) == h:
                fill = 0
            else:
                dtype = np.dtype(np.float64)
        arr = np.full((h, w), fill, dtype=dtype)
        for i, r in enumerate(rows):
            if name in r.fields:
                arr[i, : widths[i]] = r.fields[name]
        fields[name] = arr
    return AssembledScan(points=out, valid=valid, widths=widths,
                         stamps_ns=np.array([r.stamp_ns for r in rows], dtype=np.int64), sensor_poses=poses_mm,
                         fields=fields, frame_id=fixed_frame, sensor_frame=sensor_frame, end=end, index=index,
                         counters=counters)
