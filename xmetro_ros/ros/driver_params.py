"""Follow a line-scanner driver node's parameters: our scan settings from them, at start and on every change.

:class:`DriverParameterFollower` reads the parameters a :class:`~xmetro_ros.scan.driver_settings.DriverSettingsMapping`
names from the driver node (``rcl_interfaces`` ``<driver>/get_parameters`` through rclpy's
:class:`~rclpy.parameter_client.AsyncParameterClient`), and follows ``/parameter_events`` (QoS as rclcpp's
parameter events: reliable, keep last 1000, volatile), keeping only the events whose ``node`` is the driver's fully
qualified name and that touch a mapped parameter. :meth:`~DriverParameterFollower.current` gives the latest
:class:`~xmetro_ros.scan.driver_settings.DriverSettings`; :meth:`~DriverParameterFollower.status` its health for
/diagnostics (``settings_defaulted`` names the settings that took the default).

Nothing blocks an executor thread: a timer (steady clock, so it runs under ``use_sim_time`` without /clock) checks
whether the driver's parameter services are there, sends the requests, and retries an unanswered one (DDS may drop
the first response while the server's response writer is not yet matched). Each parameter is requested alone:
rclcpp's and rclpy's parameter services answer *no* value at all when one requested name is not declared. A
periodic re-read (``refresh_period_s``) recovers an event missed while /parameter_events was being matched and
notices a driver restarted with other values.
"""

from __future__ import annotations

import functools
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterEvent
from rclpy.callback_groups import CallbackGroup, MutuallyExclusiveCallbackGroup
from rclpy.client import Client
from rclpy.clock import Clock
from rclpy.clock_type import ClockType
from rclpy.parameter import parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import qos_profile_parameter_events

from ..scan.driver_settings import (
    ALL_SETTINGS,
    DriverMappingError,
    DriverSettings,
    DriverSettingsMapping,
    load_mapping,
    settings_from_parameters,
)
from ..scan.scanner import ScannerModel

__all__ = ["ERROR", "OK", "WARN", "DriverParameterFollower", "FollowerStatus"]

OK, WARN, ERROR = 0, 1, 2
_LEVEL_NAMES = ("OK", "WARN", "ERROR")


@dataclass(frozen=True)
class FollowerStatus:
    """Health of the follower for /diagnostics: ``level`` (OK, WARN, ERROR), ``message``, key/value pairs."""

    level: int
    message: str
    values: dict[str, str] = field(default_factory=dict)


def _fqn(name: str) -> str:
    name = name.strip()
    return name if name.startswith("/") else "/" + name


class DriverParameterFollower:
    """Our scan settings from a driver node's parameters, read at start and followed on ``/parameter_events``.

    Args:
        node: the rclpy node that reads (its executor runs the timer, the subscription and the responses).
        driver_node: the driver node's fully qualified name (``/lls_driver``; a missing leading ``/`` is added);
            None = the mapping's ``node``.
        mapping: a :class:`DriverSettingsMapping`, or a shipped mapping's name or a YAML path.
        callback: called (in an executor thread, without the follower's lock) with the new
            :class:`DriverSettings` whenever it changes.
        defaults: the settings used where neither the driver nor a measurement gives one: a ScanSettings or a
            ScannerModel (its ``default_settings``; it is then also the ``scanner``).
        scanner: the scanner model (range check, line width, default profile rate).
        measured: initial measured values (:meth:`set_measured`).
        retry_period_s: period of the timer that looks for the driver and retries.
        request_timeout_s: an unanswered request is dropped and sent again after this long (doubling, up to 8 s).
        refresh_period_s: re-read the parameters this often while the driver is there (0 = only at start and when
            the driver comes back).
        callback_group: for the timer, subscription and clients (default: a group of their own).
    """

    def __init__(self, node: Any, driver_node: str | None, mapping: DriverSettingsMapping | str | Path,
                 callback: Callable[[DriverSettings], None] | None = None, *, defaults: Any,
                 scanner: ScannerModel | None = None, measured: Mapping[str, float] | None = None,
                 retry_period_s: float = 0.5, request_timeout_s: float = 1.0, refresh_period_s: float = 10.0,
                 callback_group: CallbackGroup | None = None) -> None:
        self._mapping = mapping if isinstance(mapping, DriverSettingsMapping) else load_mapping(mapping)
        name = driver_node or self._mapping.node
        if not name:
            raise ValueError(f"driver mapping {self._mapping.name} names no driver node: give driver_node")
        self.driver_node = _fqn(name)
        self._node = node
        self._callback = callback
        self._defaults = defaults
        self._scanner = scanner if scanner is not None else (defaults if isinstance(defaults, ScannerModel) else None)
        self._measured: dict[str, float] = dict(measured or {})
        self._names = self._mapping.parameter_names()
        self._name_set = frozenset(self._names)
        self._request_timeout0 = float(request_timeout_s)
        self._request_timeout = self._request_timeout0
        self._refresh = float(refresh_period_s)
        self._lock = threading.Lock()
        self._raw: dict[str, Any] = {}
        self._read_once = False
        self._present = False
        self._absent_since: float | None = time.monotonic()
        self._last_read: float | None = None
        self._pending: dict[str, Any] = {}  # parameter name → future of the request in flight
        self._pending_values: dict[str, Any] = {}
        self._sent_at = 0.0
        self._generation = 0
        self._touched: set[str] = set()  # names changed by an event since the requests in flight were sent
        self.reads = 0
        self.events = 0
        self.request_timeouts = 0
        self._closed = False
        # Validate the mapping against the defaults / scanner now (a mapping needing a scanner without one raises).
        self._current = self._compute()
        group = callback_group or MutuallyExclusiveCallbackGroup()
        self._client = AsyncParameterClient(node, self.driver_node, callback_group=group)
        self._sub = node.create_subscription(ParameterEvent, "/parameter_events", self._on_event,
                                             qos_profile_parameter_events, callback_group=group)
        self._timer = node.create_timer(float(retry_period_s), self._tick, callback_group=group,
                                        clock=Clock(clock_type=ClockType.STEADY_TIME))

    # -- what the node reads ------------------------------------------------------------------------------------

    @property
    def mapping(self) -> DriverSettingsMapping:
        """The driver mapping in use."""
        return self._mapping

    @property
    def driver_present(self) -> bool:
        """True while the driver's parameter services are there."""
        with self._lock:
            return self._present

    @property
    def has_read(self) -> bool:
        """True once the driver's parameters were read (or one of them came in a parameter event)."""
        with self._lock:
            return self._read_once

    @property
    def event_publishers(self) -> int:
        """Publishers of /parameter_events matched by the follower's subscription (this node's own included)."""
        return int(self._sub.get_publisher_count())

    def current(self) -> DriverSettings:
        """The latest settings (defaults and measured values where the driver gives none)."""
        with self._lock:
            return self._current

    def set_measured(self, measured: Mapping[str, float]) -> DriverSettings:
        """Replace the measured values (ours: per mm, ms, Hz; e.g. the direction density from the posed profiles);
        returns the new settings (the callback is called when they changed)."""
        unknown = set(measured) - set(ALL_SETTINGS)
        if unknown:
            raise DriverMappingError(f"measured: unknown settings {sorted(unknown)} (known: {', '.join(ALL_SETTINGS)})")
        with self._lock:
            self._measured = dict(measured)
        return self._update()

    def set_defaults(self, defaults: Any) -> DriverSettings:
        """Replace the defaults (a ScanSettings or ScannerModel); returns the new settings."""
        with self._lock:
            self._defaults = defaults
        return self._update()

    def status(self) -> FollowerStatus:
        """Level, message and key/values for /diagnostics."""
        with self._lock:
            cur, present, read, raw = self._current, self._present, self._read_once, dict(self._raw)
            absent_since, last_read = self._absent_since, self._last_read
        now = time.monotonic()
        d = self.driver_node
        values = {"driver_node": d, "driver_mapping": self._mapping.name, "driver_present": str(present).lower(),
                  "driver_parameters_read": self.reads, "driver_parameter_events": self.events,
                  "driver_request_timeouts": self.request_timeouts,
                  "driver_last_read_s_ago": f"{now - last_read:.1f}" if last_read is not None else "never"}
        values.update({k: str(v) for k, v in cur.diagnostic_values().items()})
        defaulted = ", ".join(cur.defaulted)
        missing = [n for n in self._names if raw.get(n) is None]
        if cur.errors:
            level, msg = ERROR, f"a setting was set aside: {cur.errors[0]}"
        elif not read:
            level = WARN
            seen = present or self.events > 0  # a parameter event of the driver's says it is there too
            msg = (f"driver {d} not found: settings defaulted ({defaulted})" if not seen
                   else f"driver {d} found, reading its parameters; settings defaulted ({defaulted or 'none'})")
        elif not present:
            since = f" for {now - absent_since:.0f} s" if absent_since is not None else ""
            level, msg = WARN, f"driver {d} gone{since}: keeping the values it had"
        elif missing:
            level, msg = WARN, f"driver {d} has no parameter {', '.join(missing)}: settings defaulted ({defaulted})"
        else:
            level = OK
            taken = ", ".join(cur.from_driver) or "nothing"
            msg = f"settings from driver {d}: {taken}" + (f"; defaulted: {defaulted}" if defaulted else "")
        if self._mapping.note:
            values["driver_note"] = self._mapping.note
        return FollowerStatus(level, msg, {k: str(v) for k, v in values.items()})

    def diagnostic_status(self, name: str, hardware_id: str = "") -> DiagnosticStatus:
        """:meth:`status` as a ``diagnostic_msgs/DiagnosticStatus`` named ``name``."""
        st = self.status()
        lvl: Any = bytes([st.level]) if isinstance(DiagnosticStatus.OK, (bytes, bytearray)) else st.level
        msg = DiagnosticStatus(level=lvl, name=name, message=st.message[:500], hardware_id=hardware_id)
        msg.values = [KeyValue(key=k, value=v) for k, v in st.values.items()]
        return msg

    def close(self) -> None:
        """Stop following: destroy the timer, the subscription and the parameter clients."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            pending = list(self._pending.values())
            self._pending.clear()
        for fut in pending:
            if fut is not None:
                fut.cancel()
        self._node.destroy_timer(self._timer)
        self._node.destroy_subscription(self._sub)
        for cli in list(vars(self._client).values()):  # AsyncParameterClient has no close(): its six clients
            if isinstance(cli, Client):
                self._node.destroy_client(cli)

    # -- internals ------------------------------------------------------------------------------------------------

    def _compute(self) -> DriverSettings:
        """Settings from the current raw values (call with the lock held, or before the entities exist)."""
        if self._read_once:
            unavailable = ""
        elif self._present:
            unavailable = f"the driver {self.driver_node} is there but its parameters are not read yet"
        else:
            unavailable = f"the driver node {self.driver_node} is not found (not started, or another name)"
        return settings_from_parameters(self._mapping, self._raw, self._defaults, self._measured,
                                        scanner=self._scanner, strict=False, unavailable=unavailable,
                                        node=self.driver_node)

    def _update(self) -> DriverSettings:
        """Recompute; call the callback (outside the lock) when the result changed."""
        with self._lock:
            old = self._current
            try:
                new = self._compute()
            except DriverMappingError as e:  # e.g. an unknown measured name: keep the last settings, say why
                self._node.get_logger().error(f"driver settings not updated: {e}")
                return old
            self._current = new
        if new != old and self._callback is not None:
            self._callback(new)
        return new

    def _tick(self) -> None:
        now = time.monotonic()
        send = False
        changed = False
        with self._lock:
            if self._closed:
                return
            if self._pending:
                if now - self._sent_at < self._request_timeout:
                    return
                # Unanswered (a response dropped before the server's writer matched us, or the driver stalled).
                for fut in self._pending.values():
                    if fut is not None:
                        fut.cancel()
                self._pending.clear()
                self.request_timeouts += 1
                self._request_timeout = min(2.0 * self._request_timeout, 8.0)
            present = self._client.services_are_ready()
            if present != self._present:
                self._present = present
                self._absent_since = None if present else now
                changed = True
                if present:
                    send = True  # (re)appeared: read everything again
            elif present and (not self._read_once or (self._refresh > 0 and self._last_read is not None
                                                       and now - self._last_read >= self._refresh)):
                send = True
            if send and self._names:
                self._generation += 1
                gen = self._generation
                self._sent_at = now
                self._touched = set()
                self._pending_values = {}
                for n in self._names:
                    self._pending[n] = None
        if send and self._names:
            for n in self._names:
                fut = self._client.get_parameters([n])
                with self._lock:
                    if gen != self._generation or n not in self._pending:
                        fut.cancel()
                        continue
                    self._pending[n] = fut
                fut.add_done_callback(functools.partial(self._on_response, name=n, gen=gen))
        elif send:  # a mapping that reads nothing: being there is all
            with self._lock:
                self._read_once, self._last_read = True, now
            changed = True
        if changed:
            self._update()

    def _on_response(self, fut: Any, name: str, gen: int) -> None:
        if fut.cancelled():
            return
        try:
            resp = fut.result()
        except Exception as e:  # the client was destroyed, the context shut down
            self._node.get_logger().debug(f"get_parameters({name}) on {self.driver_node} failed: {e}")
            return
        value = parameter_value_to_python(resp.values[0]) if resp is not None and len(resp.values) == 1 else None
        with self._lock:
            if gen != self._generation or self._pending.get(name) is not fut:
                return
            del self._pending[name]
            self._pending_values[name] = value
            if self._pending:
                return
            # All answered: take them, except those an event changed since the requests went out (newer).
            for n, v in self._pending_values.items():
                if n not in self._touched:
                    self._raw[n] = v
            self._pending_values = {}
            self._read_once = True
            self._last_read = time.monotonic()
            self._request_timeout = self._request_timeout0
            self.reads += 1
        self._update()

    def _on_event(self, event: ParameterEvent) -> None:
        if event.node != self.driver_node:
            return
        upd: dict[str, Any] = {}
        for p in (*event.new_parameters, *event.changed_parameters):
            if p.name in self._name_set:
                upd[p.name] = parameter_value_to_python(p.value)
        for p in event.deleted_parameters:
            if p.name in self._name_set:
                upd[p.name] = None
        if not upd:
            return
        with self._lock:
            if self._closed:
                return
            self._raw.update(upd)
            self._touched.update(upd)  # newer than what a request in flight may answer
            self.events += 1
        self._update()
