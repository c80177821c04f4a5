"""DriverParameterFollower (xmetro_ros.ros.driver_params) over real DDS: a fake driver node (its own context, so its
own participant) declares the real driver's parameter names with the types and values the driver declares; the
follower reads them at start, follows a ``set_parameters`` change on /parameter_events, handles the driver starting
after it and leaving, and says what it defaulted and why. Run under tools/netns_run (make test does)."""

from __future__ import annotations

import itertools
import threading
import time
from typing import Any

import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter

from xmetro_ros.ros.driver_params import ERROR, OK, WARN, DriverParameterFollower
from xmetro_ros.ros.rclpy_util import NodeSpinner, wait_for
from xmetro_ros.scan.driver_settings import DriverMappingError, DriverSettings, scanner_line_width_mm
from xmetro_ros.scan.scanner import ScannerModel

SCANNER = ScannerModel.load()
TIMEOUT = 30.0
_ids = itertools.count()


class Followed:
    """A follower on a node of its own context, and every DriverSettings its callback got."""

    def __init__(self, driver: str, mapping: str, **kw: Any) -> None:
        self.seen: list[DriverSettings] = []
        self._cond = threading.Condition()
        holder: dict[str, DriverParameterFollower] = {}

        def make(ctx: Any) -> Node:
            node = Node(f"xmetro_follower_{next(_ids)}", context=ctx)
            holder["f"] = DriverParameterFollower(node, driver, mapping, self._got, defaults=SCANNER,
                                                  retry_period_s=0.1, **kw)
            return node

        self.spinner = NodeSpinner(make)
        self.f = holder["f"]

    def _got(self, s: DriverSettings) -> None:
        with self._cond:
            self.seen.append(s)
            self._cond.notify_all()

    def wait(self, pred: Any, timeout: float = TIMEOUT) -> DriverSettings:
        if not wait_for(lambda: pred(self.f.current()), timeout):
            raise TimeoutError(f"not reached in {timeout:g} s; now: {self.f.current().summary()}; "
                               f"status: {self.f.status().message}")
        return self.f.current()

    def close(self) -> None:
        self.f.close()
        self.spinner.close()


def driver(name: str, params: dict[str, Any]) -> NodeSpinner:
    """A fake driver node ``name`` that declares ``params`` (name → value, typed as the driver declares them)
    before it spins, as a C++ driver does in its constructor."""
    def make(ctx: Any) -> Node:
        node = Node(name, context=ctx)
        for k, v in params.items():
            node.declare_parameter(k, v)
        return node
    return NodeSpinner(make)


def unique(base: str) -> str:
    return f"{base}_{next(_ids)}"


@pytest.fixture
def closing():
    items: list[Any] = []
    yield items.append
    for it in reversed(items):
        it.close()


def test_reads_the_driver_at_start_and_follows_a_change_within_a_second(closing):
    name = unique("lls_driver")  # the real node is "lls_driver"; unique per test so no stale discovery interferes
    d = driver(name, {"exposure_time": 5000, "profile_period": 20000, "sensor_sensitivity": "Medium",
                      "frame_name": "scanner_tf"})
    closing(d)
    fl = Followed(name, "scancontrol_lls")
    closing(fl)
    s = fl.wait(lambda c: c.sources["exposure_ms"] == "driver")
    assert s.settings.exposure_ms == pytest.approx(5.0) and s.profile_rate_hz == pytest.approx(50.0)
    assert s.node == f"/{name}" and s.parameters == {"exposure_time": 5000, "profile_period": 20000}
    assert s.defaulted == ("lateral_density", "direction_density")
    st = fl.f.status()
    assert st.level == OK, st.message
    assert st.values["settings_defaulted"] == "lateral_density, direction_density"
    assert st.values["driver_present"] == "true" and st.values["exposure_ms_source"] == "driver"
    assert fl.seen and fl.seen[-1] == s
    diag = fl.f.diagnostic_status("xmetro: driver settings", hardware_id="lls")
    assert diag.name == "xmetro: driver settings" and {kv.key for kv in diag.values} >= {"settings_defaulted"}

    # /parameter_events: wait until the driver's events publisher is matched (discovery is asynchronous), then the
    # change must arrive within a second
    assert wait_for(lambda: fl.f.event_publishers >= 2, TIMEOUT)  # our node's own and the driver's
    t0 = time.monotonic()
    res = d.node.set_parameters([Parameter("exposure_time", value=2000)])
    assert res[0].successful
    assert wait_for(lambda: fl.f.current().settings.exposure_ms == pytest.approx(2.0), 1.0), \
        fl.f.current().summary()
    assert time.monotonic() - t0 < 1.0
    assert fl.f.events >= 1 and fl.f.current().sources["exposure_ms"] == "driver"
    # a parameter the mapping does not use changes nothing
    n = len(fl.seen)
    d.node.set_parameters([Parameter("frame_name", value="other")])
    time.sleep(0.3)
    assert len(fl.seen) == n
    # measured values (the direction density from the posed profiles) come in beside the driver's
    s = fl.f.set_measured({"direction_density": 4.2})
    assert s.sources["direction_density"] == "measured" and s.defaulted == ("lateral_density",)
    assert fl.seen[-1] == s
    with pytest.raises(DriverMappingError, match="unknown settings"):
        fl.f.set_measured({"speed": 1.0})
    assert fl.f.current() == s


def test_driver_starting_after_the_follower_and_leaving(closing):
    name = unique("lls_driver")
    fl = Followed(name, "scancontrol_lls")
    closing(fl)
    time.sleep(0.5)
    s = fl.f.current()
    st = fl.f.status()
    assert st.level == WARN and "not found" in st.message, st.message
    assert s.defaulted == ("lateral_density", "direction_density", "exposure_ms")
    assert s.settings.exposure_ms == SCANNER.default_settings.exposure_ms
    assert f"/{name} is not found" in s.messages["exposure_ms"]
    d = driver(name, {"exposure_time": 800, "profile_period": 2000})
    s = fl.wait(lambda c: c.sources["exposure_ms"] == "driver")
    assert s.settings.exposure_ms == pytest.approx(0.8) and s.profile_rate_hz == pytest.approx(500.0)
    # (the values may come first in the driver's parameter events of its declarations; the read follows)
    assert wait_for(lambda: fl.f.status().level == OK, TIMEOUT), fl.f.status().message
    d.close()  # the driver leaves: its values are kept, and the status says so
    assert wait_for(lambda: not fl.f.driver_present, TIMEOUT)
    st = fl.f.status()
    assert st.level == WARN and "gone" in st.message, st.message
    assert fl.f.current().settings.exposure_ms == pytest.approx(0.8)


def test_a_driver_without_the_parameter_defaults_it_and_says_so(closing):
    name = unique("lls_driver")
    closing(driver(name, {"profile_period": 10000}))  # no exposure_time declared
    fl = Followed(name, "scancontrol_lls")
    closing(fl)
    s = fl.wait(lambda c: c.sources["profile_rate_hz"] == "driver")
    assert fl.f.has_read
    assert s.sources["exposure_ms"] == "default"
    assert s.settings.exposure_ms == SCANNER.default_settings.exposure_ms
    assert "has no parameter exposure_time (not declared)" in s.messages["exposure_ms"]
    st = fl.f.status()
    assert st.level == WARN and "has no parameter exposure_time" in st.message, st.message
    assert "exposure_ms" in st.values["settings_defaulted"]


def test_a_bad_driver_value_is_an_error_and_falls_back(closing):
    name = unique("lls_driver")
    closing(driver(name, {"exposure_time": 60000, "profile_period": 100000}))  # 60 ms: past the scanner's 50 ms
    fl = Followed(name, "scancontrol_lls")
    closing(fl)
    s = fl.wait(lambda c: bool(c.errors))
    assert s.sources["exposure_ms"] == "default" and s.profile_rate_hz == pytest.approx(10.0)
    st = fl.f.status()
    assert st.level == ERROR and "outside the scanner's range" in st.message, st.message


def test_samxl_resolution_written_back_by_the_driver_and_events_of_other_nodes_ignored(closing):
    name = unique("scancontrol_driver")
    d = driver(name, {"resolution": 0, "serial": "", "frame_id": "scancontrol", "partial_profile_point_count": -1})
    closing(d)
    other = driver(unique("other_driver"), {"resolution": 0})  # same parameter name on another node
    closing(other)
    fl = Followed(name, "scancontrol_samxl")
    closing(fl)
    fl.wait(lambda c: fl.f.has_read)
    s = fl.f.current()
    assert s.sources["lateral_density"] == "default" and "resolution = 0 means not known yet" in \
        s.messages["lateral_density"]
    assert "set_exposure_duration" in s.messages["exposure_ms"]
    assert wait_for(lambda: fl.f.event_publishers >= 3, TIMEOUT)
    other.node.set_parameters([Parameter("resolution", value=640)])
    time.sleep(0.3)
    assert fl.f.current().sources["lateral_density"] == "default"
    # the driver applies the device's resolution and writes it back to its parameter (InitResolution)
    d.node.set_parameters([Parameter("resolution", value=1280)])
    s = fl.wait(lambda c: c.sources["lateral_density"] == "driver", 5.0)
    assert s.settings.lateral_density == pytest.approx(1280 / scanner_line_width_mm(SCANNER))
