"""The node's processing worker: a bounded queue of received scans, one worker thread judging them with the
:class:`~xmetro_ros.ros.core.XmetroCore`, publication of the results, and the watchdog that abandons and replaces a
worker past ``max_processing_time``.

A mixin of the node's wiring (:class:`xmetro_ros.ros.node.XmetroWiring`): it uses the node's ``core``, ``diag``,
publishers (``pub_dev``, ``pub_corr``, ``pub_quality``, ``pub_diag``, ``pub_reference``, ``pub_cad``) and logger.
Processing in its own thread keeps the services and parameter changes responsive whatever the executor.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any

from sensor_msgs.msg import PointCloud2

from ..msg import ReferenceCheck, ScanQuality
from .convert import stamp_to_ns
from .core import XmetroCore
from .diagnostics import DiagnosticsState
from .posed_scans import PosedScan
from .rclpy_util import NodeMixin

__all__ = ["ScanWorker"]


class ScanWorker(NodeMixin):
    """Queue, worker thread, publication and watchdog of the node (see the module docstring)."""

    core: XmetroCore | None
    diag: DiagnosticsState | None
    pub_dev: Any
    pub_corr: Any
    pub_quality: Any
    pub_diag: Any
    pub_reference: Any
    pub_cad: Any
    _outputs: list[Any]

    def _init_worker_state(self) -> None:
        # (scan, receipt time, from the reference_scan topic, the PosedScan of a scan assembled from profiles)
        self._queue: deque[tuple[PointCloud2, float, bool, PosedScan | None]] = deque()
        self._qmax = 1
        self._cv = threading.Condition()
        self._stop = False
        self._worker: threading.Thread | None = None
        self._diag_lock = threading.Lock()
        # Watchdog state (under self._cv): the scan in processing (start, msg, t0, reference), the live worker's
        # token, abandoned worker threads still running.
        self._busy: tuple[float, PointCloud2, float, bool, PosedScan | None] | None = None
        self._token: object = object()
        self._abandoned: list[threading.Thread] = []

    def _enqueue(self, core: XmetroCore, diag: DiagnosticsState, msg: PointCloud2, t0: float,
                 reference: bool, posed: PosedScan | None = None) -> None:
        """Queue a received scan; when the queue is full the oldest is dropped, counted and answered
        ``QUEUE_OVERFLOW``."""
        dropped = None
        with self._cv:
            if self._stop:
                return
            if len(self._queue) >= self._qmax:
                dropped = self._queue.popleft()
                diag.on_dropped()
            self._queue.append((msg, t0, reference, posed))
            self._update_queue_diag()
            self._cv.notify()
        if dropped is not None:
            text = f"the node's processing queue was full ({self._qmax}): scan dropped unjudged"
            self.get_logger().warning(f"{text} (stamp {stamp_to_ns(dropped[0].header.stamp)} ns)")
            self._publish_quality(core.unjudged(dropped[0], "QUEUE_OVERFLOW", text, dropped[1], dropped[3]).quality)
            if dropped[3] is not None:
                self._posed_done(dropped[3], judged=False)

    def _stop_worker(self) -> None:
        with self._cv:
            self._stop = True
            self._queue.clear()
            self._busy = None
            self._cv.notify_all()
        if self._worker is not None and self._worker is not threading.current_thread():
            self._worker.join(timeout=10.0)
        self._worker = None

    def _update_queue_diag(self) -> None:
        """Caller holds self._cv."""
        if self.diag is not None:
            self.diag.on_queue(len(self._queue), int(self._busy is not None))

    def _start_worker(self) -> threading.Thread:
        with self._cv:
            token = object()
            self._token = token
            t = threading.Thread(target=self._work, args=(token,), name="xmetro-worker", daemon=True)
            t.start()
            return t

    def _work(self, token: object) -> None:
        while True:
            with self._cv:
                while not self._queue and not self._stop and self._token is token:
                    self._cv.wait(0.5)
                if self._stop or self._token is not token:
                    return
                msg, t0, reference, posed = self._queue.popleft()
                self._busy = (time.monotonic(), msg, t0, reference, posed)
                self._update_queue_diag()
            try:
                self._process(msg, t0, token, reference, posed)
            except Exception as e:
                try:
                    self.get_logger().error(f"unexpected failure while publishing: {type(e).__name__}: {e}")
                except Exception:
                    return
            finally:
                with self._cv:
                    if self._token is token:
                        self._busy = None
                        self._update_queue_diag()

    def _process(self, msg: PointCloud2, t0: float, token: object, reference: bool = False,
                 posed: PosedScan | None = None) -> None:
        core = self.core
        if core is None:
            return
        out = core.judge(msg, t0, deadline=time.monotonic() + float(core.values["max_processing_time"]),
                         reference=reference, posed=posed)
        with self._cv:
            if self._token is not token:
                return  # abandoned by the watchdog: its scan was already answered TIMEOUT
            self._busy = None
            self._update_queue_diag()
        q = out.quality
        if out.deviations is not None:
            self.pub_dev.publish(out.deviations)
            # ~/corrected is built only when someone takes it (a volatile topic: a reader not yet matched would not
            # get it either)
            if self.pub_corr.get_subscription_count() > 0 and out.corrected is not None:
                self.pub_corr.publish(out.corrected)
        q.processing_latency = time.monotonic() - t0
        if q.verdict == ScanQuality.VERDICT_ERROR:
            self.get_logger().error(out.log)
        elif q.settings_defaulted:
            self.get_logger().warning(out.log)
        else:
            self.get_logger().debug(out.log)
        if q.error_code == ScanQuality.ERROR_TIMEOUT and self.diag is not None:
            self.diag.on_timeout()
        if out.reference is not None:
            self._publish_reference(out.reference)
        self._publish_cad(out)
        self._answer(q)
        if posed is not None:
            self._posed_done(posed, judged=True)

    def _publish_cad(self, out: Any) -> None:
        """Publish a scan's CAD map; a failed comparison is logged and goes to /diagnostics (WARN until the next
        scan's comparison succeeds); the scan's other outputs were published already."""
        if out.cad is not None:
            self.pub_cad.publish(out.cad)
            self.get_logger().debug(out.cad_log)
        elif out.cad_error:
            self.get_logger().warning(out.cad_error)
        if self.diag is not None and (out.cad is not None or out.cad_error):
            self.diag.on_cad(out.cad_error or out.cad_log, ok=not out.cad_error)

    def _publish_reference(self, ref: ReferenceCheck) -> None:
        """Publish a reference scan's check; its state goes to /diagnostics (published at once on a change)."""
        self.pub_reference.publish(ref)
        if ref.state == ReferenceCheck.STATE_WARN:
            self.get_logger().warning(ref.message)
        elif ref.state == ReferenceCheck.STATE_MISMATCH:
            self.get_logger().error(ref.message)
        diag = self.diag
        if diag is not None:
            diag.on_reference(int(ref.state), ref.message, int(ref.reference_scans))
            if diag.level() != diag.published_level:
                self._publish_diag()

    def _answer(self, q: ScanQuality) -> None:
        """Count a judged scan, publish its quality (with the counters) and /diagnostics on a level change."""
        diag = self.diag
        if diag is None:
            return
        before = diag.published_level
        diag.on_result(int(q.verdict), q.message, q.processing_latency, bool(q.settings_defaulted))
        self._publish_quality(q)
        if diag.level() != before:
            self._publish_diag()

    def _publish_quality(self, q: ScanQuality) -> None:
        if self.diag is not None:
            for k, v in self.diag.counters().items():
                setattr(q, k, v)
        self.pub_quality.publish(q)

    def _supervise(self) -> None:
        """Watchdog supervisor (diagnostics timer): flag a scan past ``max_processing_time``; abandon and replace a
        worker past twice the bound (at most one abandoned thread alive: Python cannot kill it)."""
        core, diag = self.core, self.diag
        if core is None or diag is None:
            return
        bound = float(core.values["max_processing_time"])
        now = time.monotonic()
        abandoned = None
        with self._cv:
            self._abandoned = [t for t in self._abandoned if t.is_alive()]
            busy = self._busy
            reason = ""
            if busy is not None and now - busy[0] > bound:
                stamp = stamp_to_ns(busy[1].header.stamp)
                reason = (f"worker stalled: scan stamped {stamp} ns processing for {now - busy[0]:.1f} s "
                          f"> max_processing_time {bound:g} s")
                if now - busy[0] > 2 * bound and not self._abandoned and not self._stop:
                    abandoned = busy
                    if self._worker is not None:
                        self._abandoned.append(self._worker)
                    self._busy = None
                    self._worker = self._start_worker()
                    self._update_queue_diag()
            if self._abandoned:
                reason = "; ".join(x for x in (reason, f"{len(self._abandoned)} abandoned worker thread(s) still "
                                               "running (Python cannot stop one; its result will be discarded)") if x)
        diag.set_stalled(reason)
        if abandoned is not None:
            start, msg, t0, _reference, posed = abandoned
            text = (f"processing exceeded max_processing_time {bound:g} s: worker abandoned after "
                    f"{now - start:.1f} s, scan answered unjudged")
            self.get_logger().error(f"watchdog: {text} (stamp {stamp_to_ns(msg.header.stamp)} ns)")
            diag.on_timeout(abandoned_worker=True)
            self._answer(core.unjudged(msg, "TIMEOUT", text, t0, posed).quality)
            if posed is not None:
                self._posed_done(posed, judged=True)  # answered (TIMEOUT), as a scan abandoned on the scan topic

    def _publish_diag(self) -> None:
        self._supervise()
        with self._diag_lock:
            try:
                if self.diag is not None and self._outputs:
                    self.pub_diag.publish(self.diag.build(self.get_clock().now().to_msg()))
            except Exception:
                pass

    def _posed_done(self, posed: PosedScan, judged: bool) -> None:
        """A scan assembled from profiles was answered (``judged``) or dropped by the queue: the profile stream's
        accounting (overridden by the profile input)."""

    def queue_length(self) -> int:
        return len(self._queue)
