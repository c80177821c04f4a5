"""Health of ``xmetro_node`` on ``/diagnostics`` (diagnostic_msgs/DiagnosticArray), following diagnostic_updater's
conventions: one DiagnosticStatus named ``"<node name>: scan processing"`` (the node's actual name, remaps included),
``hardware_id`` = the scanner id, key/value pairs for the counters, published every ``diagnostics_period`` and at
once when the level changes.

Level (the most severe reason wins; the message lists every reason above OK, most severe first, up to 1,000
characters):

- ERROR: no usable model (degraded start); the worker is stalled (a scan past ``max_processing_time`` that did not
  come back, or an abandoned worker thread still running); the last scan could not be processed (ScanQuality
  ERROR); scans arrive but no ScannerSettings ever did (every scan runs on the configured defaults);
- WARN: scans lost in transport in the last ``loss_warn_period`` seconds (default ``LOSS_HOLD_S``; DDS sample-lost
  events, or gaps in a publisher's sequence numbers), with the likely cause and its fix for the subscription's
  reliability;
  no scan for ``scan_timeout`` seconds (stale input: a dead scanner or a lost connection; also before the
  first scan); the last scan was judged WARN or RESCAN, or its settings were defaulted; the reference drift monitor
  says WARN (held until ``~/reset_reference``), or the last reference scan did not show the declared sphere; the
  configured pose model set (``pose_model_dir``) could not be used (the primary judges every scan);
- OK otherwise.

Values: node-level scan accounting (``scans_received`` = ``scans_judged`` + ``scans_dropped`` + ``scans_queued`` +
``scans_in_progress``; ``scans_lost`` before the callback), frequency (diagnostic_updater's FrequencyStatus keys:
events in window, events since startup, duration of window, actual frequency), latency (last and p50 / max over
the last 100 scans, ms), the watchdog's counters, the last verdict and message, the reference monitor's state.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

__all__ = ["FREQUENCY_WINDOW_S", "LOSS_HOLD_S", "TASK_NAME", "DiagnosticsState", "lost_scans_reason", "status_name"]

TASK_NAME = "scan processing"
FREQUENCY_WINDOW_S = 10.0
#: A loss keeps /diagnostics at WARN this long (s) by default: long enough for a person or a monitor to see it.
LOSS_HOLD_S = 60.0
OK, WARN, ERROR = 0, 1, 2
_VERDICT_LEVEL = {0: OK, 1: WARN, 2: WARN, 3: ERROR}
# ReferenceCheck.STATE_* (kept as numbers: this module builds no xmetro_ros message)
_REF_WARN, _REF_MISMATCH = 2, 3
_REF_NAMES: dict[int | None, str] = {0: "WARMUP", 1: "OK", 2: "WARN", 3: "MISMATCH"}


def status_name(node_name: str) -> str:
    """diagnostic_updater's status name: ``"<node name>: <task>"``."""
    return f"{node_name}: {TASK_NAME}"


class DiagnosticsState:
    """Thread-safe counters and health of the node, turned into a DiagnosticArray by :meth:`build`.

    Args:
        node_name: the node's name (``Node.get_name()``, after remapping).
        hardware_id: the scanner id.
        model_id: the model set's id ("" when degraded).
        degraded: why the node runs without a model ("" = it has one).
        scan_timeout: seconds without a scan before WARN (stale input).
        pose_model_id, pose_model_error: the second model set's id, or why the configured one is not used (WARN).
    """

    def __init__(self, node_name: str, hardware_id: str, model_id: str, degraded: str = "",
                 scan_timeout: float = 5.0, cad_mesh: str = "", cad_error: str = "", pose_model_id: str = "",
                 pose_model_error: str = "") -> None:
        self.name = status_name(node_name)
        self.hardware_id = hardware_id
        self.model_id = model_id
        self.degraded = degraded
        self.scan_timeout = float(scan_timeout)
        self.received = 0
        self.processed = 0
        self.failed = 0
        self.dropped = 0
        self.lost = 0
        self.dds_lost_events = 0
        self.scan_reliability = "best_effort"  # the scan subscription's, set by the node (reliability: auto)
        self.loss_warn_period = LOSS_HOLD_S    # the node's parameter of that name
        self._last_loss: float | None = None
        self.timeouts = 0
        self.workers_abandoned = 0
        self.settings_received = 0
        self.queued = 0
        self.in_progress = 0
        self.stalled = ""                   # set by the node's supervisor: why the worker is considered stalled
        self.last_verdict: int | None = None
        self.last_message = "waiting for scans"
        self.last_defaulted = False
        self.reference_state: int | None = None  # ReferenceCheck.STATE_* of the last reference scan
        self.reference_message = ""
        self.reference_scans = 0
        self.cad_error = cad_error          # the configured CAD part (cad_mesh) could not be loaded: ERROR
        # the last scan's CAD comparison (its log line), or why it failed
        self.cad_state = ("off" if not cad_mesh else "failed to load" if cad_error
                          else f"{cad_mesh}: no scan compared yet")
        self.cad_failed = False             # the last scan's CAD comparison failed (WARN until one succeeds)
        self.pose_model_id = pose_model_id  # the second model set (scans outside the primary's domain), "" = none
        self.pose_model_error = pose_model_error  # one was configured but could not be used: WARN
        self._start = time.monotonic()
        self._last_scan: float | None = None
        self._latencies: deque[float] = deque(maxlen=100)
        self._times: deque[float] = deque(maxlen=1000)
        self._lock = threading.Lock()
        self.published_level: int | None = None
        # Profile streams (profile_input): their accounting, shown as values, and the latest drop (WARN for
        # loss_warn_period); their scans' settings come from the stream, so no ScannerSettings is expected.
        self.profile_values: dict[str, Any] = {}
        self.profile_problem = ""
        self._last_profile_problem: float | None = None
        self.settings_from_stream = False

    # ------------------------------------------------------------------ events
    def on_received(self) -> None:
        with self._lock:
            self.received += 1
            now = time.monotonic()
            self._last_scan = now
            self._times.append(now)

    def on_dropped(self) -> None:
        with self._lock:
            self.dropped += 1

    def on_lost(self, n: int, dds_event: bool = False) -> None:
        """``n`` scans lost before the callback (sequence-number gaps; ``dds_event``: a DDS sample-lost event,
        counted apart since the gaps already include what DDS reports)."""
        with self._lock:
            if dds_event:
                self.dds_lost_events += int(n)
            else:
                self.lost += int(n)
            if n > 0:
                self._last_loss = time.monotonic()

    def on_settings(self) -> None:
        with self._lock:
            self.settings_received += 1

    def on_queue(self, queued: int, in_progress: int) -> None:
        with self._lock:
            self.queued, self.in_progress = int(queued), int(in_progress)

    def on_timeout(self, abandoned_worker: bool = False) -> None:
        with self._lock:
            self.timeouts += 1
            self.workers_abandoned += int(abandoned_worker)

    def set_stalled(self, reason: str) -> None:
        with self._lock:
            self.stalled = reason

    def on_result(self, verdict: int, message: str, latency_s: float, defaulted: bool) -> None:
        with self._lock:
            if verdict == 3:
                self.failed += 1
            else:
                self.processed += 1
            self.last_verdict = verdict
            self.last_message = message
            self.last_defaulted = defaulted
            self._latencies.append(latency_s)

    def on_reference(self, state: int, message: str, reference_scans: int) -> None:
        """The last reference scan's check (ReferenceCheck.STATE_*: 0 warm-up, 1 OK, 2 WARN, 3 mismatch). A WARN
        holds until :meth:`on_reference_reset` (the monitor itself holds it too)."""
        with self._lock:
            if self.reference_state == _REF_WARN and state == _REF_MISMATCH:
                self.reference_message = f"{self.reference_message} (and: {message})"
                return
            self.reference_state, self.reference_message = int(state), message
            self.reference_scans = int(reference_scans)

    def on_cad(self, text: str, ok: bool) -> None:
        """The last scan's CAD comparison: its summary line, or (``ok`` False) why it failed."""
        with self._lock:
            self.cad_state, self.cad_failed = text, not ok

    def on_reference_reset(self) -> None:
        with self._lock:
            self.reference_state, self.reference_message, self.reference_scans = None, "", 0

    def on_profiles(self, values: dict[str, Any], problem: str = "") -> None:
        """The profile stream's accounting (values shown as they are) and, when given, a drop just reported."""
        with self._lock:
            self.profile_values = dict(values)
            if problem:
                self.profile_problem = problem
                self._last_profile_problem = time.monotonic()

    def counters(self) -> dict[str, int]:
        """The scan accounting now: received, judged, dropped, lost."""
        with self._lock:
            return {"scans_received": self.received, "scans_judged": self.processed + self.failed,
                    "scans_dropped": self.dropped, "scans_lost": self.lost}

    # ------------------------------------------------------------------ level
    def _reasons(self, now: float) -> list[tuple[int, str]]:
        """(level, reason) pairs, unsorted; caller holds the lock."""
        out: list[tuple[int, str]] = []
        if self.degraded:
            out.append((ERROR, f"degraded: {self.degraded}"))
        if self.stalled:
            out.append((ERROR, self.stalled))
        if self.received and not self.settings_received and not self.settings_from_stream:
            out.append((ERROR, "no ScannerSettings ever arrived: every scan runs on the configured defaults"))
        since = now - (self._last_scan if self._last_scan is not None else self._start)
        if since > self.scan_timeout:
            what = "no scan for" if self._last_scan is not None else "no scan received in"
            out.append((WARN, f"stale: {what} {since:.1f} s (scan_timeout {self.scan_timeout:g} s)"))
        if self._last_loss is not None and now - self._last_loss <= self.loss_warn_period:
            out.append((WARN, lost_scans_reason(self.lost, self.dds_lost_events, self.scan_reliability)))
        if self._last_profile_problem is not None and now - self._last_profile_problem <= self.loss_warn_period:
            out.append((WARN, self.profile_problem))
        if self.pose_model_error:
            out.append((WARN, self.pose_model_error))
        if self.cad_error:
            out.append((ERROR, self.cad_error))
        elif self.cad_failed:
            out.append((WARN, self.cad_state))
        if self.reference_state in (_REF_WARN, _REF_MISMATCH):
            out.append((WARN, self.reference_message))
        if self.last_verdict is not None:
            lvl = _VERDICT_LEVEL[self.last_verdict]
            if self.last_defaulted:
                lvl = max(lvl, WARN)
            out.append((lvl, self.last_message))
        return out

    def level(self) -> int:
        with self._lock:
            return max((lv for lv, _ in self._reasons(time.monotonic())), default=OK)

    def build(self, stamp: Any) -> DiagnosticArray:
        """The DiagnosticArray now (``stamp``: builtin_interfaces/Time)."""
        with self._lock:
            lat = np.asarray(self._latencies, dtype=float) * 1e3
            now = time.monotonic()
            reasons = sorted(self._reasons(now), key=lambda r: -r[0])
            lvl = reasons[0][0] if reasons else OK
            # every reason above OK, the most severe first: a lesser one can be the cause of a worse (scans lost in
            # transport behind "no ScannerSettings ever arrived" when the one that got through ran on defaults)
            shown = [r for lv, r in reasons if lv > OK] if lvl > OK else [r for _, r in reasons[:1]]
            msg = "; ".join(dict.fromkeys(shown)) or self.last_message
            window = min(FREQUENCY_WINDOW_S, now - self._start)
            events = sum(1 for t in self._times if now - t <= FREQUENCY_WINDOW_S)
            values = {
                "model_id": self.model_id,
                "pose_model_id": self.pose_model_id or self.pose_model_error or "none",
                "degraded": self.degraded or "no",
                "scans_received": self.received,
                "scans_judged": self.processed + self.failed,
                "scans_processed": self.processed,
                "scans_failed": self.failed,
                "scans_dropped": self.dropped,
                "scans_queued": self.queued,
                "scans_in_progress": self.in_progress,
                "scans_lost": self.lost,
                "dds_message_lost_events": self.dds_lost_events,
                "scans_timed_out": self.timeouts,
                "workers_abandoned": self.workers_abandoned,
                "settings_received": self.settings_received,
                "Events in window": events,
                "Events since startup": self.received,
                "Duration of window (s)": f"{window:.3f}",
                "Actual frequency (Hz)": f"{events / window:.3f}" if window > 0 else "0.000",
                "seconds_since_last_scan": f"{now - self._last_scan:.3f}" if self._last_scan is not None else "never",
                "scan_timeout_s": f"{self.scan_timeout:g}",
                "latency_last_ms": f"{lat[-1]:.1f}" if len(lat) else "n/a",
                "latency_p50_ms": f"{np.median(lat):.1f}" if len(lat) else "n/a",
                "latency_max_ms": f"{lat.max():.1f}" if len(lat) else "n/a",
                "last_verdict": ("OK", "WARN", "RESCAN", "ERROR")[self.last_verdict]
                if self.last_verdict is not None else "none",
                "settings_defaulted": str(self.last_defaulted).lower(),
                "worker_stalled": self.stalled or "no",
                "reference_state": _REF_NAMES.get(self.reference_state, "none"),
                "reference_scans": self.reference_scans,
                "reference_message": self.reference_message or "none",
                "cad": self.cad_error or self.cad_state,
                **self.profile_values,
            }
        st = DiagnosticStatus(level=_level_value(lvl), name=self.name, message=msg[:1000],
                              hardware_id=self.hardware_id)
        st.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        arr = DiagnosticArray()
        arr.header.stamp = stamp
        arr.status = [st]
        self.published_level = lvl
        return arr


def lost_scans_reason(gaps: int, dds_events: int, reliability: str) -> str:
    """The /diagnostics reason for scans lost before the node's callback, with the fix a user can apply.

    Args:
        gaps: scans missing from publishers' sequence numbers; dds_events: DDS sample-lost events (Fast DDS reports
            them for samples a best-effort reader could not reassemble); reliability: the scan subscription's.
    """
    what = f"scans lost in transport ({gaps} by sequence gaps, {dds_events} DDS sample-lost events)"
    if reliability == "best_effort":
        return (f"{what}: a best-effort subscription loses a whole cloud when one fragment is dropped, as Fast DDS's "
                "default transports do from a few hundred kB; publish the scans reliable (reliability auto "
                "follows) or give both processes the shared-memory profile config/fastdds_localhost.xml "
                "(FASTDDS_DEFAULT_PROFILES_FILE) — docs/dds.md")
    return (f"{what}: the reliable subscription's queue (keep last 5) overflowed: scans arrive faster than the "
            "node takes them")


def _level_value(lvl: int) -> Any:
    """DiagnosticStatus.level is a byte field: bytes in rclpy's generated code."""
    return bytes([lvl]) if isinstance(DiagnosticStatus.OK, (bytes, bytearray)) else lvl
