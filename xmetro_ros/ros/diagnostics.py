"""Health of ``xmetro_node`` on ``/diagnostics`` (diagnostic_msgs/DiagnosticArray): counters, rates, latency.

One DiagnosticStatus ``xmetro_node: scan processing`` (hardware_id = scanner id). Level:
- ERROR: no usable model (degraded start), or the last scan could not be processed (ScanQuality ERROR);
- WARN: the last scan was judged WARN or RESCAN, or its settings were defaulted;
- OK otherwise (also before the first scan: "waiting for scans").
Values: model_id, degraded reason, scans received / processed / failed / dropped, scan rate (Hz, last 10 s),
latency (last and p50 / max over the last 100 scans, ms), last verdict and message. The node publishes it every
``diagnostics_period`` and at once when the level changes.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

__all__ = ["STATUS_NAME", "DiagnosticsState"]

STATUS_NAME = "xmetro_node: scan processing"
_VERDICT_LEVEL = {0: DiagnosticStatus.OK, 1: DiagnosticStatus.WARN, 2: DiagnosticStatus.WARN,
                  3: DiagnosticStatus.ERROR}


class DiagnosticsState:
    """Thread-safe counters of the node, turned into a DiagnosticArray by :meth:`build`."""

    def __init__(self, hardware_id: str, model_id: str, degraded: str = "") -> None:
        self.hardware_id = hardware_id
        self.model_id = model_id
        self.degraded = degraded
        self.received = 0
        self.processed = 0
        self.failed = 0
        self.dropped = 0
        self.last_verdict: int | None = None
        self.last_message = "waiting for scans"
        self.last_defaulted = False
        self._latencies: deque[float] = deque(maxlen=100)
        self._times: deque[float] = deque(maxlen=200)
        self._lock = threading.Lock()
        self.published_level: int | None = None

    def on_received(self) -> None:
        with self._lock:
            self.received += 1
            self._times.append(time.monotonic())

    def on_dropped(self) -> None:
        with self._lock:
            self.dropped += 1

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

    def level(self) -> int:
        if self.degraded:
            return _as_int(DiagnosticStatus.ERROR)
        if self.last_verdict is None:
            return _as_int(DiagnosticStatus.OK)
        lvl = _as_int(_VERDICT_LEVEL[self.last_verdict])
        if self.last_defaulted:
            lvl = max(lvl, _as_int(DiagnosticStatus.WARN))
        return lvl

    def build(self, stamp: Any) -> DiagnosticArray:
        """The DiagnosticArray now (``stamp``: builtin_interfaces/Time)."""
        with self._lock:
            lat = np.asarray(self._latencies, dtype=float) * 1e3
            now = time.monotonic()
            recent = [t for t in self._times if now - t <= 10.0]
            rate = (len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) > 1 and recent[-1] > recent[0] \
                else 0.0
            lvl = self.level()
            if self.degraded:
                msg = f"degraded: {self.degraded}"
            else:
                msg = self.last_message
            values = {
                "model_id": self.model_id,
                "degraded": self.degraded or "no",
                "scans_received": str(self.received),
                "scans_processed": str(self.processed),
                "scans_failed": str(self.failed),
                "scans_dropped": str(self.dropped),
                "scan_rate_hz": f"{rate:.3f}",
                "latency_last_ms": f"{lat[-1]:.1f}" if len(lat) else "n/a",
                "latency_p50_ms": f"{np.median(lat):.1f}" if len(lat) else "n/a",
                "latency_max_ms": f"{lat.max():.1f}" if len(lat) else "n/a",
                "last_verdict": ("OK", "WARN", "RESCAN", "ERROR")[self.last_verdict]
                if self.last_verdict is not None else "none",
                "settings_defaulted": str(self.last_defaulted).lower(),
            }
        st = DiagnosticStatus(level=_level_value(lvl), name=STATUS_NAME, message=msg[:500],
                              hardware_id=self.hardware_id)
        st.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        arr = DiagnosticArray()
        arr.header.stamp = stamp
        arr.status = [st]
        self.published_level = lvl
        return arr


def _as_int(v: Any) -> int:
    return v[0] if isinstance(v, (bytes, bytearray)) else int(v)


def _level_value(lvl: int) -> Any:
    """DiagnosticStatus.level is a byte field: bytes in rclpy's generated code."""
    return bytes([lvl]) if isinstance(DiagnosticStatus.OK, (bytes, bytearray)) else lvl
