"""Scan settings from a driver's ROS parameters (xmetro_ros.scan.driver_settings, ROS-free): each shipped mapping
against the parameters its driver declares (names, types and defaults as read in the driver's source), the unit
conversions, the precedence driver → measured → default with its messages, and the errors."""

from __future__ import annotations

import fnmatch
import math
from pathlib import Path

import pytest

from xmetro_ros.scan.driver_settings import (
    ALL_SETTINGS,
    DriverMappingError,
    DriverSettingsMapping,
    list_mappings,
    load_mapping,
    scanner_line_width_mm,
    settings_from_parameters,
)
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings

ROOT = Path(__file__).resolve().parents[1]
SCANNER = ScannerModel.load()  # xm-ls90: stand-off 90 mm, fan 70°, defaults 10 / 4 / 0.5, exposure range [0.005, 50]
DEFAULTS = SCANNER.default_settings

# Every parameter IGMR-RWTH/scancontrol_lls declares (include/scancontrol_lls_driver/parameters.hpp at 3c67d76), with
# its declared default: integers for the times (µs), strings for the names.
LLS_DECLARED = {
    "data_topic": "scancontrol_lls/scanPoints", "discovery_service": "scancontrol_lls/discoverDevices",
    "interface_service": "scancontrol_lls/setInterface", "exposure_time": 1000, "profile_period": 10000,
    "configuration_file_path": "", "sensor_sensitivity": "Medium", "sensor_trigger_source": "FreeRun",
    "frame_name": "scanner_tf", "start_scan": "scancontrol_lls/startScan", "stop_scan": "scancontrol_lls/stopScan",
    "frame_buffer_size": 256, "connect_on_startup": True, "peak_filter_enable": False, "peak_filter_min_width": 1,
    "peak_filter_max_width": 1024, "peak_filter_min_intensity": 0, "peak_filter_max_intensity": 1023,
}
# Every parameter sam-xl/scancontrol declares (micro_epsilon_scancontrol_driver/src/driver.cpp at a5fa1fa).
SAMXL_DECLARED = {
    "resolution": 0, "serial": "", "frame_id": "scancontrol", "topic_name": "scancontrol_pointcloud",
    "partial_profile_start_point": 0, "partial_profile_start_point_data": 0, "partial_profile_point_count": -1,
    "partial_profile_data_width": 8,
}


def test_shipped_mappings_name_the_drivers_parameters():
    assert list_mappings() == ["scancontrol_lls", "scancontrol_samxl"]
    lls, samxl = load_mapping("scancontrol_lls"), load_mapping("scancontrol_samxl")
    assert lls.node == "/lls_driver" and samxl.node == "/scancontrol_driver"
    assert lls.parameter_names() == ("exposure_time", "profile_period")
    assert samxl.parameter_names() == ("resolution",)
    for m, declared in ((lls, LLS_DECLARED), (samxl, SAMXL_DECLARED)):
        assert set(m.parameter_names()) <= set(declared)
        for entry in m.settings.values():  # the driver declares an integer, which the mapping accepts
            assert type(declared[entry.parameter]) is int and "integer" in entry.types
        assert m.source and m.driver
        # every setting is either mapped or documented as absent
        assert set(m.settings) | set(m.absent) == set(ALL_SETTINGS)
    assert "GetResolution" in lls.absent["lateral_density"]
    assert "set_exposure_duration" in samxl.absent["exposure_ms"]


def test_scancontrol_lls_declared_defaults_and_params_file():
    m = load_mapping("scancontrol_lls")
    r = settings_from_parameters(m, LLS_DECLARED, SCANNER)
    assert r.settings.exposure_ms == pytest.approx(1.0)  # 1000 µs
    assert r.profile_rate_hz == pytest.approx(100.0)  # 1e6 / 10000 µs
    assert r.from_driver == ("exposure_ms", "profile_rate_hz")
    assert r.defaulted == ("lateral_density", "direction_density") and r.settings_defaulted
    assert r.settings.lateral_density == DEFAULTS.lateral_density
    assert r.parameters == {"exposure_time": 1000, "profile_period": 10000}
    assert "GetResolution" in r.messages["lateral_density"] and "default" in r.messages["lateral_density"]
    assert "exposure_time = 1000 µs" in r.messages["exposure_ms"]
    # the shipped params file of the driver (config/lls_driver.params.yaml): 5000 µs, 20000 µs
    r = settings_from_parameters(m, {**LLS_DECLARED, "exposure_time": 5000, "profile_period": 20000}, SCANNER)
    assert r.settings.exposure_ms == pytest.approx(5.0) and r.profile_rate_hz == pytest.approx(50.0)
    assert r.errors == ()


def test_scancontrol_samxl_resolution_gives_the_lateral_density():
    m = load_mapping("scancontrol_samxl")
    width = scanner_line_width_mm(SCANNER)
    assert width == pytest.approx(2 * 90.0 * math.tan(math.radians(35.0)))
    r = settings_from_parameters(m, {**SAMXL_DECLARED, "resolution": 1280}, SCANNER)
    assert r.settings.lateral_density == pytest.approx(1280 / width)
    assert r.from_driver == ("lateral_density",)
    assert r.defaulted == ("direction_density", "exposure_ms")
    assert "set_exposure_duration" in r.messages["exposure_ms"]
    assert r.sources["profile_rate_hz"] == "default" and r.profile_rate_hz == SCANNER.profile_rate_hz
    # resolution 0 (declared default: "the device's first") is not known yet: defaulted, and said so
    r = settings_from_parameters(m, SAMXL_DECLARED, SCANNER)
    assert r.sources["lateral_density"] == "default"
    assert "resolution = 0 means not known yet" in r.messages["lateral_density"]
    # a known head: the measuring-range width as a constant of a copy of the mapping
    d = {"name": "scancontrol_29x0_25", "settings": {"lateral_density": {
        "parameter": "resolution", "types": ["integer"], "unset": [0], "line_width_mm": 25.0}}}
    r = settings_from_parameters(DriverSettingsMapping.from_dict(d), {"resolution": 640}, DEFAULTS)
    assert r.settings.lateral_density == pytest.approx(640 / 25.0)


def test_samxl_needs_the_scanner_model_for_its_line_width():
    m = load_mapping("scancontrol_samxl")
    with pytest.raises(DriverMappingError, match="scanner model"):
        settings_from_parameters(m, {"resolution": 1280}, DEFAULTS)  # a ScanSettings gives no line width
    r = settings_from_parameters(m, {"resolution": 1280}, DEFAULTS, scanner=SCANNER)
    assert r.sources["lateral_density"] == "driver"


def test_precedence_driver_then_measured_then_default():
    m = load_mapping("scancontrol_lls")
    measured = {"direction_density": 4.2, "exposure_ms": 2.0, "lateral_density": 12.0}
    r = settings_from_parameters(m, {"exposure_time": 5000}, SCANNER, measured)
    assert r.sources == {"lateral_density": "measured", "direction_density": "measured", "exposure_ms": "driver",
                         "profile_rate_hz": "default"}
    assert r.settings == ScanSettings(12.0, 4.2, 5.0)
    assert "measured" in r.messages["direction_density"] and "set by the motion" in r.messages["direction_density"]
    assert r.defaulted == () and not r.settings_defaulted and r.defaulted_message() == ""
    # the driver's parameter missing (not declared): the measured value, else the default, and why
    r = settings_from_parameters(m, {"profile_period": 10000}, SCANNER, {"direction_density": 4.2})
    assert r.sources["exposure_ms"] == "default" and r.settings.exposure_ms == DEFAULTS.exposure_ms
    assert "no parameter exposure_time (not declared)" in r.messages["exposure_ms"]
    assert "exposure_ms" in r.defaulted_message() and "lateral_density" in r.defaulted_message()
    r = settings_from_parameters(m, {}, SCANNER, unavailable="the driver node /lls_driver is not found")
    assert "/lls_driver is not found" in r.messages["exposure_ms"]


def test_defaults_as_scan_settings_or_scanner_and_no_rate_without_scanner():
    m = load_mapping("scancontrol_lls")
    r = settings_from_parameters(m, {}, ScanSettings(8.0, 3.0, 1.0))
    assert r.settings == ScanSettings(8.0, 3.0, 1.0)
    assert r.profile_rate_hz is None and r.sources["profile_rate_hz"] == "none"
    assert r.diagnostic_values()["profile_rate_hz"] == "n/a"
    with pytest.raises(TypeError, match="ScanSettings or a ScannerModel"):
        settings_from_parameters(m, {}, {"exposure_ms": 1.0})


@pytest.mark.parametrize("value, match", [
    ("5000", "must be an integer .µs., got string '5000'"),
    (5000.0, "must be an integer .µs., got double 5000.0"),
    (True, "must be an integer .µs., got bool True"),
    ([5000], "got array"),
    (-5, "must be a positive finite number"),
    (0, "must be a positive finite number"),
])
def test_a_bad_type_or_value_is_a_clear_error(value, match):
    m = load_mapping("scancontrol_lls")
    with pytest.raises(DriverMappingError, match=match) as e:
        settings_from_parameters(m, {"exposure_time": value}, SCANNER)
    assert e.value.setting == "exposure_ms" and e.value.parameter == "exposure_time"
    assert isinstance(e.value, ValueError)
    # not strict: said in errors, the setting falls back (to the measured value here)
    r = settings_from_parameters(m, {"exposure_time": value}, SCANNER, {"exposure_ms": 2.0}, strict=False)
    assert r.sources["exposure_ms"] == "measured" and r.settings.exposure_ms == 2.0
    assert len(r.errors) == 1 and "exposure_time" in r.errors[0]
    assert "set aside" in r.messages["exposure_ms"]
    assert r.diagnostic_values()["settings_errors"] == r.errors[0]


def test_out_of_the_scanners_range():
    m = load_mapping("scancontrol_lls")
    with pytest.raises(DriverMappingError, match=r"exposure_ms = 60 is outside the scanner's range \[0.005, 50\] "
                                                 r"\(from exposure_time = 60000 µs\)"):
        settings_from_parameters(m, {"exposure_time": 60000}, SCANNER)
    # the range given explicitly wins over the scanner's
    r = settings_from_parameters(m, {"exposure_time": 60000}, SCANNER, ranges={"exposure_ms": (0.001, 100.0)})
    assert r.settings.exposure_ms == pytest.approx(60.0)
    r = settings_from_parameters(m, {"exposure_time": 60000}, SCANNER, strict=False)
    assert r.sources["exposure_ms"] == "default" and "outside the scanner's range" in r.errors[0]
    # a measured value is checked as well
    with pytest.raises(DriverMappingError, match="measured direction_density = 80 is outside"):
        settings_from_parameters(m, {}, SCANNER, {"direction_density": 80.0})
    with pytest.raises(DriverMappingError, match="unknown setting 'speed'"):
        settings_from_parameters(m, {}, SCANNER, {"speed": 1.0})


def test_enum_table_and_unit_conversions():
    d = {"name": "enum_driver", "node": "enum_driver", "settings": {
        "exposure_ms": {"parameter": "exposure_level", "types": ["integer"], "unit": "µs",
                        "table": {0: 100, 1: 500, 2: 2000}, "scale": 0.001},
        "lateral_density": {"parameter": "spacing", "types": ["double"], "unit": "mm", "reciprocal": 1.0},
        "profile_rate_hz": {"parameter": "mode", "types": ["string"], "unit": "Hz",
                            "table": {"slow": 100, "fast": 4000}},
        "direction_density": {"parameter": "encoder_step_m", "unit": "m", "reciprocal": 0.001}}}
    m = DriverSettingsMapping.from_dict(d)
    assert m.node == "/enum_driver"
    r = settings_from_parameters(m, {"exposure_level": 1, "spacing": 0.05, "mode": "fast", "encoder_step_m": 0.0002},
                                 SCANNER)
    assert r.settings.exposure_ms == pytest.approx(0.5)
    assert r.settings.lateral_density == pytest.approx(20.0)
    assert r.settings.direction_density == pytest.approx(5.0)  # 1 / 0.2 mm
    assert r.profile_rate_hz == 4000.0 and r.defaulted == ()
    with pytest.raises(DriverMappingError, match=r"exposure_level = 7 is not in the mapping's table \(0, 1, 2\)"):
        settings_from_parameters(m, {"exposure_level": 7}, SCANNER)
    with pytest.raises(DriverMappingError, match="must be a string"):
        settings_from_parameters(m, {"mode": 2}, SCANNER)
    assert "table[value] × 0.001" in m.settings["exposure_ms"].describe()


@pytest.mark.parametrize("d, match", [
    ({"settings": {"exposure_ms": {"parameter": "e", "speed": 1}}}, "unknown keys"),
    ({"setings": {}}, "unknown keys"),
    ({"settings": {"shutter": {"parameter": "e"}}}, "unknown setting 'shutter'"),
    ({"settings": {"exposure_ms": {"unit": "us"}}}, "'parameter'"),
    ({"settings": {"exposure_ms": {"parameter": "e", "scale": 0.001, "reciprocal": 1e6}}}, "either"),
    ({"settings": {"exposure_ms": {"parameter": "e", "scale": 0}}}, "positive finite"),
    ({"settings": {"exposure_ms": {"parameter": "e", "types": ["float"]}}}, "types must be"),
    ({"settings": {"exposure_ms": {"parameter": "e", "types": ["string"]}}}, "needs a 'table'"),
    ({"settings": {"exposure_ms": {"parameter": "e", "line_width_mm": 25.0}}}, "lateral_density only"),
    ({"settings": {"exposure_ms": {"parameter": "e"}}, "absent": {"exposure_ms": "x"}}, "both mapped and absent"),
    ([1, 2], "expected a mapping"),
])
def test_malformed_mapping(d, match):
    with pytest.raises(DriverMappingError, match=match):
        DriverSettingsMapping.from_dict(d, name="bad")


def test_load_by_name_or_path(tmp_path):
    with pytest.raises(DriverMappingError, match=r"no driver mapping named 'keyence_ljv' \(shipped: "
                                                 r"scancontrol_lls, scancontrol_samxl"):
        load_mapping("keyence_ljv")
    p = tmp_path / "my_head.yaml"
    p.write_text("node: my_driver\nsettings:\n  exposure_ms: {parameter: exposure_us, types: [integer, double], "
                 "scale: 0.001}\n")
    m = load_mapping(p)
    assert m.name == "my_head" and m.node == "/my_driver" and m.parameter_names() == ("exposure_us",)
    assert load_mapping(str(p)).settings == m.settings
    r = settings_from_parameters(m, {"exposure_us": 750.0}, DEFAULTS)
    assert r.settings.exposure_ms == pytest.approx(0.75)
    p.write_text("settings: [")
    with pytest.raises(DriverMappingError, match="not valid YAML"):
        load_mapping(p)
    with pytest.raises(DriverMappingError, match="cannot be read"):
        load_mapping(tmp_path / "none.yaml")


def test_diagnostic_values_name_the_defaulted_settings():
    r = settings_from_parameters(load_mapping("scancontrol_lls"), {"exposure_time": 5000, "profile_period": 20000},
                                 SCANNER, {"direction_density": 4.0})
    v = r.diagnostic_values()
    assert v["settings_defaulted"] == "lateral_density"
    assert v["exposure_ms"] == "5 ms" and v["exposure_ms_source"] == "driver"
    assert v["direction_density_source"] == "measured" and v["profile_rate_hz"] == "50 Hz"
    assert v["settings_errors"] == "none"
    assert r.summary().count(";") == len(ALL_SETTINGS) - 1


def test_shipped_mappings_are_packaged():
    """The pip route carries config/drivers/*.yaml (pyproject package-data); colcon installs the whole config/."""
    import tomllib

    data = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["xmetro_ros"]
    for p in sorted((ROOT / "config" / "drivers").glob("*.yaml")):
        rel = f"config/drivers/{p.name}"
        # (fnmatch's * also matches '/', setuptools' does not: compare the depth too)
        assert any(fnmatch.fnmatch(rel, g) and rel.count("/") == g.count("/") for g in data), rel
    assert "install(DIRECTORY config DESTINATION" in (ROOT / "CMakeLists.txt").read_text()
