"""A profile stream without DDS: profile and tf messages in, assembled scans and drop reports out, with the
stream's accounting. Shared by the live node (:mod:`xmetro_ros.ros.profile_input`, which only wires topics to it)
and ``xmetro predict`` of a bag of profiles + tf, so both assemble and report alike.

Accounting: ``received`` = ``judged`` + ``dropped`` (Σ by reason; idle profiles between scans included) +
``waiting`` (held for tf, in the scan being built, or in the node's queue); ``lost``: sent by a publisher but never
received (gaps in its sequence numbers: transport, or a reader history that overflowed); :meth:`ProfileStream.values`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

from ..scan.assembly import AssembledScan, DropReason, ProfileAssembler, ScanEnd, ScanTrigger
from ..scan.tf_buffer import TransformBuffer, TransformRecord
from .cloud import CloudFormatError
from .convert import ns_to_stamp, stamp_to_ns
from .posed_scans import drop_message
from .profile_msgs import profile_from_cloud

__all__ = ["REPORT_PERIOD_S", "ProfileStream", "StreamError", "error_quality", "records_from_tf", "scan_header",
           "stream_from_values"]

#: Drops of one reason are reported at most this often (each report counts all since the last one), seconds.
REPORT_PERIOD_S = 0.5


def records_from_tf(msg: Any) -> list[TransformRecord]:
    """The ``geometry_msgs/TransformStamped`` of a ``tf2_msgs/TFMessage`` as records (metres, quaternion x, y, z, w)."""
    out = []
    for t in msg.transforms:
        tr, q = t.transform.translation, t.transform.rotation
        out.append(TransformRecord(stamp_ns=stamp_to_ns(t.header.stamp), parent=t.header.frame_id,
                                   child=t.child_frame_id, translation=(tr.x, tr.y, tr.z),
                                   rotation=(q.x, q.y, q.z, q.w)))
    return out


@dataclass
class StreamError:
    """Profiles that will not be judged: the ScanQuality to publish (header, error code name, message)."""

    header: Header
    code: str
    message: str


def _header(stamp_ns: int, frame_id: str) -> Header:
    return Header(stamp=ns_to_stamp(int(stamp_ns)), frame_id=frame_id)


def scan_header(scan: AssembledScan) -> Header:
    """The header of an assembled scan's outputs: the fixed frame, the first profile's stamp."""
    return _header(int(scan.stamps_ns[0]), scan.frame_id)


class ProfileStream:
    """The assembler, its transform buffer and the reports of one profile stream.

    Args:
        assembler: the :class:`~xmetro_ros.scan.assembly.ProfileAssembler` (its buffer is fed by :meth:`tf`).
        min_range_m: profile points with z below this are no return (None: only non-finite ones).
        context_rows: 0 = each scan the assembler completes is judged on its own; > 0 = streaming: each is judged
            with this many rows of the chunks before and after it, and only its own rows are published.

    Not thread-safe: the node calls it under one lock.
    """

    def __init__(self, assembler: ProfileAssembler, min_range_m: float | None = None, context_rows: int = 0) -> None:
        self.assembler = assembler
        self.context_rows = int(context_rows)
        self._pending: AssembledScan | None = None  # streaming: the chunk waiting for the next one
        self._tail: AssembledScan | None = None  # streaming: the last rows of the chunk judged before
        self.tf_buffer = assembler.tf
        self.min_range_m = min_range_m
        self.counts = {"received": 0, "undecodable": 0, "queued": 0, "judged": 0, "queue_dropped": 0,
                       "cut_by_gap": 0, "not_judged": 0, "lost": 0}
        self._reported: dict[DropReason, int] = dict.fromkeys(DropReason, 0)
        self._report_time: dict[DropReason, float] = {}
        self.clock: tuple[int, float] | None = None  # (newest profile stamp ns, the caller's time it came, s)

    # ------------------------------------------------------------------ input
    def profile(self, msg: PointCloud2, now_s: float) -> tuple[list[AssembledScan], list[StreamError]]:
        """One profile message at the caller's time ``now_s`` (monotonic or log time, seconds)."""
        return self.profiles([msg], now_s)

    def profiles(self, msgs: list[PointCloud2], now_s: float) -> tuple[list[AssembledScan], list[StreamError]]:
        """Profile messages in arrival order, decoded one by one and posed together (one tf lookup: the node feeds
        what arrived every few milliseconds)."""
        decoded, errors = [], []
        for msg in msgs:
            self.counts["received"] += 1
            try:
                decoded.append(profile_from_cloud(msg, min_range_m=self.min_range_m))
            except CloudFormatError as e:
                self.counts["undecodable"] += 1
                errors.append(StreamError(msg.header, e.code, f"profile not decoded: {e}"))
        if decoded:
            self.clock = (max(int(p.stamp_ns) for p in decoded), now_s)
        scans, more = self._out(self.assembler.add_many(decoded), now_s)
        return scans, errors + more

    def lost(self, n: int) -> None:
        """``n`` profiles a publisher sent that never reached the subscription (its sequence numbers' gaps)."""
        self.counts["lost"] += int(n)

    def tf(self, msg: Any, static: bool, now_s: float) -> tuple[list[AssembledScan], list[StreamError], int]:
        """One TFMessage; also returns how many of its transforms were refused (non-finite, zero quaternion or an
        unnamed frame: the others are stored)."""
        refused = self.tf_buffer.set_transforms(records_from_tf(msg), static=static)
        if not self.assembler.counters.pending:
            return [], [], refused
        scans, errors = self._out(self.assembler.poll(), now_s)
        return scans, errors, refused

    def signal(self, start: bool, now_s: float) -> tuple[list[AssembledScan], list[StreamError]]:
        """Start or stop a scan (``scan_trigger: signal``); ValueError with the reason for another trigger."""
        return self._out(self.assembler.start() if start else self.assembler.stop(), now_s)

    def poll(self, now_s: float) -> tuple[list[AssembledScan], list[StreamError]]:
        """Advance the stream's clock to the newest profile's stamp plus the time since it came (tf timeouts, gaps
        and windows end without a newer profile)."""
        now_ns = None
        if self.clock is not None:
            stamp, seen = self.clock
            now_ns = stamp + round((now_s - seen) * 1e9)
        return self._out(self.assembler.poll(now_ns), now_s)

    def flush(self, now_s: float) -> tuple[list[AssembledScan], list[StreamError]]:
        """End of the stream (a bag's end): held profiles are dropped with their reason, the open scan closed;
        every drop not yet reported is."""
        scans, errors = self._out(self.assembler.flush(), now_s)
        if self._pending is not None:  # streaming: the held chunk, with the rows before it only
            rows = self._pending.shape[0]
            scans.append(self._emit(None))
            self.counts["queued"] += rows
        return scans, errors + self.report_drops(now_s, force=True)

    # ------------------------------------------------------------------ scans and drops
    def _out(self, scans: list[AssembledScan], now_s: float) -> tuple[list[AssembledScan], list[StreamError]]:
        keep, errors = [], []
        if self.context_rows:  # chunks judged with their neighbours' rows (streaming)
            scans = self._windows(scans, now_s)
        for scan in scans:
            rows = scan.own_rows
            if scan.end is ScanEnd.GAP and self.assembler.trigger.kind != "gap" and not self.context_rows:
                self.counts["cut_by_gap"] += rows
                errors.append(StreamError(scan_header(scan), "PROFILE_GAP", (
                    f"scan of {rows} profiles cut short by a pause in the stream longer than trigger_gap "
                    f"({self.assembler.trigger.gap_s:g} s): not judged; profiles stamped {int(scan.stamps_ns[0])} "
                    f"to {int(scan.stamps_ns[-1])} ns")))
                continue
            self.counts["queued"] += rows
            keep.append(scan)
        return keep, errors + self.report_drops(now_s)

    def _windows(self, chunks: list[AssembledScan], now_s: float) -> list[AssembledScan]:
        """Streaming: each chunk the assembler completes is held until the next one of the same pass arrives, then
        judged with ``context_rows`` rows of the chunk before it and of the one after it (its border rows get
        their neighbours for the normals); the last chunk of a pass (a gap, a stop, the end) with those before it
        only. The latency of a row is therefore at most two chunks plus the judging."""
        out: list[AssembledScan] = []
        for c in chunks:
            if self._pending is not None:
                # the next chunk of the same pass, or the first of another (a pause between them)
                out.append(self._emit(c if not self._paused_before(c) else None))
            self._pending = c
            if c.end not in (ScanEnd.COUNT, ScanEnd.WINDOW, ScanEnd.MAX_ROWS):  # the pass ended with this chunk
                out.append(self._emit(None))
        if self._pending is not None and self._stalled(now_s):
            out.append(self._emit(None))  # its pass ended (no profile since) before a next chunk came
        return out

    def _paused_before(self, chunk: AssembledScan) -> bool:
        """A pause longer than the gap rule between the held chunk's last row and ``chunk``'s first."""
        gap = self.assembler.trigger.gap_s
        assert self._pending is not None
        return gap is not None and int(chunk.stamps_ns[0]) - int(self._pending.stamps_ns[-1]) > round(gap * 1e9)

    def _stalled(self, now_s: float) -> bool:
        """No profile at all for longer than the gap rule allows (stream time): the held chunk's pass has ended."""
        gap = self.assembler.trigger.gap_s
        if self._pending is None or gap is None or self.clock is None:
            return False
        return now_s - self.clock[1] > gap

    def _emit(self, after: AssembledScan | None) -> AssembledScan:
        """The held chunk with its context: the tail of the chunk before, the head of ``after`` (None: none)."""
        own = self._pending
        assert own is not None
        k = self.context_rows
        parts = [p for p in (self._tail, own, after.rows(0, min(k, after.shape[0])) if after is not None else None)
                 if p is not None]
        window = AssembledScan.concat(parts)
        start = self._tail.shape[0] if self._tail is not None else 0
        window.core_rows = (start, start + own.shape[0])
        n = own.shape[0]
        self._tail = own.rows(max(0, n - k), n) if after is not None else None
        self._pending = None
        return window

    def report_drops(self, now_s: float, force: bool = False) -> list[StreamError]:
        """Drops since the last report, one :class:`StreamError` per reason (IDLE is not an error), at most every
        :data:`REPORT_PERIOD_S` per reason unless ``force``."""
        out = []
        for reason, n in self.assembler.counters.dropped.items():
            new = n - self._reported[reason]
            if new <= 0 or reason is DropReason.IDLE:
                continue
            if not force and now_s - self._report_time.get(reason, -1e18) < REPORT_PERIOD_S:
                continue
            self._reported[reason] = n
            self._report_time[reason] = now_s
            last = next((d for d in reversed(self.assembler.recent_drops) if d.reason is reason), None)
            code, text = drop_message(reason, new, last.detail if last is not None else "")
            out.append(StreamError(_header(last.stamp_ns if last is not None else 0,
                                           last.frame_id if last is not None else ""), code, text))
        return out

    def done(self, rows: int, judged: bool) -> None:
        """``rows`` profiles of a queued scan were answered (``judged``: any verdict) or dropped by the queue."""
        self.counts["queued"] -= rows
        self.counts["judged" if judged else "queue_dropped"] += rows

    def not_judged(self, rows: int) -> None:
        """A queued scan's profiles that could not be turned into a scan to judge (counted dropped)."""
        self.counts["queued"] -= rows
        self.counts["not_judged"] += rows

    def values(self) -> dict[str, Any]:
        """The accounting as /diagnostics values."""
        c, pc = self.assembler.counters, self.counts
        extra = ("undecodable", "queue_dropped", "cut_by_gap", "not_judged")
        dropped = sum(c.dropped.values()) + sum(pc[k] for k in extra)
        by_reason = [f"{r.value.lower()} {n}" for r, n in c.dropped.items() if n] + \
            [f"{k} {pc[k]}" for k in extra if pc[k]]
        return {
            "profiles_received": pc["received"],
            "profiles_judged": pc["judged"],
            "profiles_dropped": dropped,
            "profiles_waiting": c.pending + c.in_progress + pc["queued"],
            "profiles_dropped_by_reason": ", ".join(by_reason) or "none",
            "profiles_lost": pc["lost"],
            "profile_scans_assembled": c.scans,
            "tf_frames": len(self.tf_buffer.frames),
        }


def error_quality(err: StreamError, model_id: str) -> Any:
    """The ERROR ScanQuality of a :class:`StreamError` (the live node publishes it, ``xmetro predict`` writes it)."""
    from .messages import error_code_value, new_quality

    q = new_quality(err.header, model_id, None, False)
    q.verdict = q.VERDICT_ERROR
    q.error_code = error_code_value(err.code)
    q.message = err.message
    return q


def stream_from_values(values: dict[str, Any]) -> ProfileStream:
    """The stream the node's parameters describe (``scan_trigger``, ``trigger_*``, ``tf_*``, ``*_scan_rows``,
    ``fixed_frame``, ``sensor_frame``, ``profile_columns``, ``profile_min_range``)."""
    kind = str(values["scan_trigger"])
    gap = float(values["trigger_gap"]) or None
    speed = float(values["trigger_min_speed"]) or None
    if kind == "gap" and gap is None and speed is None:
        gap = 0.05
    trigger = ScanTrigger(kind, count=int(values["trigger_count"]) if kind == "count" else None,  # type: ignore[arg-type]
                          window_s=float(values["trigger_window"]) if kind == "window" else None,
                          gap_s=gap, min_speed_m_s=speed)
    buf = TransformBuffer(cache_time_ns=round(float(values["tf_cache_time"]) * 1e9),
                          max_extrapolation_ns=round(float(values["tf_max_extrapolation"]) * 1e9))
    asm = ProfileAssembler(buf, str(values["fixed_frame"]), trigger, sensor_frame=str(values["sensor_frame"]) or None,
                           tf_timeout_s=float(values["tf_timeout"]), max_rows=int(values["max_scan_rows"]),
                           min_rows=int(values["min_scan_rows"]), columns=str(values["profile_columns"]))  # type: ignore[arg-type]
    return ProfileStream(asm, float(values["profile_min_range"]) or None, int(values["stream_context_rows"]))
