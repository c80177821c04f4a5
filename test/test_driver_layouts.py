"""Every driver layout decoded (issue 24): the clouds real laser line scanner drivers publish (test/driver_emulators.py,
byte for byte) through our validator, ``xyz_fields``, ``ros.profile_msgs.profile_from_cloud``, a tf chain and the
ProfileAssembler; the organized ones (a Mech-Eye batch, an area sensor) through ``cloud_to_scan``."""

from __future__ import annotations

import array

import numpy as np
import pytest
from driver_emulators import DRIVERS, DROPPING, LLS_OUT_OF_RANGE_Z_M, ORGANIZED, Emulated, plane_profile
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rclpy.qos import ReliabilityPolicy
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import PointField

from xmetro_ros.ros.cloud import CloudFormatError, validate_cloud, xyz_fields
from xmetro_ros.ros.convert import cloud_to_scan
from xmetro_ros.ros.profile_msgs import profile_from_cloud
from xmetro_ros.scan.assembly import Profile, ProfileAssembler, ScanEnd, ScanTrigger
from xmetro_ros.scan.geometry import HeadPose
from xmetro_ros.scan.scanner import ScanSettings
from xmetro_ros.scan.tf_buffer import TransformBuffer

NAMES = sorted(DRIVERS)
MS = 1_000_000
T0 = 10_000 * MS  # stream start, ns


def _mask(w: int, seed: int, frac: float = 0.1) -> np.ndarray:
    m = np.random.default_rng(seed).random(w) < frac
    m[w // 3: w // 3 + 7] = True  # a hole
    return m


def _emulate(name: str, w: int = 300, seed: int = 0, **kw) -> Emulated:
    return DRIVERS[name].builder(plane_profile(w, invalid=_mask(w, seed)), T0 + 123_456_789, **kw)


def _buffer_bytes(msg) -> np.ndarray:
    return np.frombuffer(msg.data, dtype=np.uint8)


# -- the layouts as the drivers' sources write them ----------------------------------------------------------------

LAYOUTS = {  # name: (point_step, [(field, offset, datatype)], is_dense, frame_id, reliable, depth)
    "scancontrol_samxl": (32, [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 16, 7)], True, "scancontrol",
                          True, 10),
    "scancontrol_lls": (26, [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("m0", 12, 6), ("m1", 16, 6), ("width", 20, 4),
                             ("intensity", 22, 4), ("threshold", 24, 4)], True, "scanner_tf", False, 5),
    "keyence_ljv": (16, [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], False, "sensor_optical_frame", True, 10),
    "wecat3d_cpp": (16, [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], False, "laser_frame", True, 10),
    "wecat3d_py": (12, [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], False, "map", True, 10),
    "gocator": (32, [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("rgb", 16, 7)], True, "gocator", True, 10),
}


def test_registry_covers_every_layout():
    assert set(LAYOUTS) == set(DRIVERS)
    assert set(ORGANIZED) == {"mech_eye_batch", "area_sensor"}


@pytest.mark.parametrize("name", NAMES)
def test_message_layout_and_qos_as_the_driver_publishes(name):
    step, fields, dense, frame, reliable, depth = LAYOUTS[name]
    e = _emulate(name)
    m = e.msg
    assert (m.height, m.point_step, m.is_bigendian, m.is_dense, m.header.frame_id) == (1, step, False, dense, frame)
    assert [(f.name, f.offset, f.datatype, f.count) for f in m.fields] == [(*f, 1) for f in fields]
    assert m.row_step == m.width * step and len(m.data) == m.row_step
    assert m.width == (300 if name not in DROPPING else int(np.isfinite(e.points).all(axis=1).sum()))
    qos = DRIVERS[name].qos
    assert qos.reliability == (ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT)
    assert qos.depth == depth


@pytest.mark.parametrize("name", ["scancontrol_samxl", "keyence_ljv", "gocator"])
def test_pcl_padding_bytes_are_written(name):
    """pcl's points carry data[3] = 1.0f at byte 12: not a field, and the decoder never reads it."""
    m = _emulate(name).msg
    pad = np.frombuffer(m.data, dtype="<f4").reshape(m.width, m.point_step // 4)[:, 3]
    assert (pad == 1.0).all()


# -- (a) our validator and xyz_fields ------------------------------------------------------------------------------

@pytest.mark.parametrize("name", NAMES)
def test_validator_accepts_and_xyz_fields_reads_the_driver_values(name):
    e = _emulate(name, seed=1)
    validate_cloud(e.msg)  # is_dense true or false, +inf / NaN inside: accepted
    xyz, _ = xyz_fields(e.msg)
    assert xyz.dtype == np.float32 and np.shares_memory(xyz, _buffer_bytes(e.msg))  # a view, every layout
    ok = np.isfinite(e.points).all(axis=1)
    np.testing.assert_array_equal(xyz[ok].astype(np.float64), e.points[ok])
    if name == "scancontrol_lls":
        # The IGMR driver does not mark a no-return: the SDK's out-of-range value comes through finite.
        assert np.isfinite(xyz[~ok]).all() and (xyz[~ok, 2] == np.float32(LLS_OUT_OF_RANGE_Z_M)).all()
    else:
        assert not np.isfinite(xyz[~ok]).all(axis=1).any()  # +inf or NaN, whatever the driver's convention


def test_all_no_return_profiles_per_convention():
    """A profile without any return: NO_VALID_POINTS for the validator where the driver marks no-returns,
    EMPTY_CLOUD where it drops them (then an empty profile, not an error, for the decoder); the IGMR layout cannot be
    told from a valid one by the validator (its values are finite)."""
    nothing = plane_profile(64, invalid=np.ones(64, bool))
    for name in NAMES:
        msg = DRIVERS[name].builder(nothing, T0).msg
        if name == "scancontrol_lls":
            validate_cloud(msg)
            assert np.isnan(profile_from_cloud(msg, min_range_m=0.0325).points).all()
            continue
        with pytest.raises(CloudFormatError) as ei:
            validate_cloud(msg)
        assert ei.value.code == ("EMPTY_CLOUD" if name in DROPPING else "NO_VALID_POINTS")
        if name in DROPPING:
            prof = profile_from_cloud(msg)  # width 0: a profile with no return (issue 24), kept as a row
            assert prof.points.shape == (0, 3) and prof.stamp_ns > 0
        else:
            assert np.isnan(profile_from_cloud(msg).points).all()  # a profile with no return is no error


# -- (b) profile_from_cloud ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", NAMES)
def test_profile_from_cloud_gives_the_points_and_fields(name):
    e = _emulate(name, seed=2)
    p = profile_from_cloud(e.msg, **e.decode_kwargs)
    assert isinstance(p, Profile)
    assert p.stamp_ns == e.stamp_ns and p.frame_id == e.msg.header.frame_id
    np.testing.assert_array_equal(p.points.astype(np.float64), e.points)  # NaN rows where no return
    assert set(p.fields) == set(e.fields)
    for k, v in e.fields.items():
        assert p.fields[k].dtype.kind == "f"
        np.testing.assert_array_equal(p.fields[k], v)
    p64 = profile_from_cloud(e.msg, dtype=np.float64, **e.decode_kwargs)
    assert p64.points.dtype == np.float64
    np.testing.assert_array_equal(p64.points, e.points)  # float32 metres → float64, exact


@pytest.mark.parametrize("name", NAMES)
def test_points_are_a_view_when_every_point_returns(name):
    e = DRIVERS[name].builder(plane_profile(100), T0)
    p = profile_from_cloud(e.msg)
    if name == "scancontrol_samxl":  # its last two points are always +inf (the sensor's timestamp): one copy
        assert not np.shares_memory(p.points, _buffer_bytes(e.msg))
        assert np.isnan(p.points[-2:]).all() and np.isfinite(p.points[:-2]).all()
    else:
        assert np.shares_memory(p.points, _buffer_bytes(e.msg))
    for k, a in p.fields.items():  # float fields are views, integer fields float64 copies
        assert np.shares_memory(a, _buffer_bytes(e.msg)) == (k in ("intensity", "rgb") and name != "scancontrol_lls")


def test_a_lying_is_dense_is_ignored():
    for name in ("scancontrol_samxl", "keyence_ljv"):
        e = _emulate(name, seed=3)
        e.msg.is_dense = True
        p = profile_from_cloud(e.msg)
        bad = ~np.isfinite(e.points).all(axis=1)
        assert bad.any() and np.isnan(p.points[bad]).all() and np.isfinite(p.points[~bad]).all()


def test_any_non_finite_coordinate_is_a_no_return_row():
    e = DRIVERS["keyence_ljv"].builder(plane_profile(6), T0)
    raw = np.frombuffer(e.msg.data, dtype="<f4").reshape(6, 4)
    raw[1, 0], raw[2, 1], raw[3, 2], raw[4, 2] = -np.inf, np.nan, np.inf, -np.inf
    p = profile_from_cloud(e.msg)
    assert np.isnan(p.points[1:5]).all() and np.isfinite(p.points[[0, 5]]).all()


def test_the_encoder_y_of_a_wecat3d_publisher_is_kept():
    """Both weCat3D publishers write the encoder position into y: a sensor-frame y the decoder keeps (with tf
    motion as well it would count the travel twice: such a stream needs encoder 0 or the y removed upstream)."""
    p = profile_from_cloud(DRIVERS["wecat3d_py"].builder(plane_profile(10), T0, encoder=500).msg)
    assert np.allclose(p.points[:, 1], 500 * 0.02e-3)
    p = profile_from_cloud(DRIVERS["wecat3d_cpp"].builder(plane_profile(10), T0, encoder=7).msg)
    assert np.allclose(p.points[:, 1], 7e-3)


def test_big_endian_and_padded_rows_decode_the_same():
    e = _emulate("keyence_ljv", seed=4)
    be = e.msg.__class__(header=e.msg.header, height=1, width=e.msg.width, fields=e.msg.fields, is_bigendian=True,
                         point_step=16, row_step=16 * e.msg.width + 8, is_dense=False)
    rec = np.frombuffer(e.msg.data, dtype="<f4").astype(">f4").tobytes() + b"\0" * 8
    be.data = array.array("B", rec)
    np.testing.assert_array_equal(profile_from_cloud(be).points.astype(np.float64), e.points)


def _broken(kind: str):
    e = _emulate("scancontrol_samxl", w=20)
    m = e.msg
    if kind == "truncated":
        m.data = array.array("B", bytes(m.data)[:-5])
    elif kind == "no_z":
        m.fields = [f for f in m.fields if f.name != "z"]
    elif kind == "int_x":
        m.fields[0].datatype = PointField.UINT32
    elif kind == "overlap":
        m.fields[3].offset = 6
    elif kind == "duplicate":
        m.fields[3].name = "y"
    elif kind == "organized":
        m.height, m.width, m.row_step = 2, 10, 320
    elif kind == "empty":  # width 0 with data left: not the empty profile of a dropping driver
        m.width, m.row_step = 0, 0
    elif kind == "step_too_small":
        m.point_step = 12
    return m


@pytest.mark.parametrize(("kind", "code"), [
    ("truncated", "BAD_LAYOUT"), ("no_z", "MISSING_FIELD"), ("int_x", "MISSING_FIELD"), ("overlap", "BAD_LAYOUT"),
    ("duplicate", "DUPLICATE_FIELD"), ("organized", "BAD_LAYOUT"), ("empty", "EMPTY_CLOUD"),
    ("step_too_small", "BAD_LAYOUT"),
])
def test_malformed_messages_raise_typed_errors(kind, code):
    with pytest.raises(CloudFormatError) as ei:
        profile_from_cloud(_broken(kind))
    assert ei.value.code == code


def test_bad_arguments():
    e = _emulate("scancontrol_lls", w=10)
    with pytest.raises(CloudFormatError) as ei:
        profile_from_cloud(e.msg, fields=["snr"])
    assert ei.value.code == "MISSING_INPUT_FIELD"
    with pytest.raises(CloudFormatError):
        profile_from_cloud(e.msg, fields=["z"])
    assert set(profile_from_cloud(e.msg, fields=["intensity"]).fields) == {"intensity"}
    with pytest.raises(TypeError):
        profile_from_cloud(object())  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="float"):
        profile_from_cloud(e.msg, dtype=np.int32)


@settings(max_examples=150, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(name=st.sampled_from(NAMES), w=st.integers(1, 80), seed=st.integers(0, 2**32 - 1),
       frac=st.sampled_from([0.0, 0.1, 0.5, 0.9]))
def test_random_masks_decode_exactly(name, w, seed, frac):
    rng = np.random.default_rng(seed)
    pts = np.stack([np.sort(rng.uniform(-0.03, 0.03, w)), np.zeros(w), rng.uniform(0.05, 0.12, w)], axis=1)
    mask = rng.random(w) < frac
    pts[mask] = np.nan
    e = DRIVERS[name].builder(pts, T0 + int(rng.integers(0, 10**9)))
    if e.msg.width == 0:  # every point dropped: a profile with no return
        assert profile_from_cloud(e.msg).points.shape == (0, 3)
        return
    p = profile_from_cloud(e.msg, dtype=np.float64, **e.decode_kwargs)
    np.testing.assert_array_equal(p.points, e.points)
    kept = np.isfinite(p.points).all(axis=1)
    assert np.array_equal(np.flatnonzero(kept), np.flatnonzero(np.isfinite(e.points).all(axis=1)))
    assert e.columns is not None and np.array_equal(mask[e.columns[kept]], np.zeros(kept.sum(), bool))
    for k, v in e.fields.items():
        np.testing.assert_array_equal(p.fields[k], v)


# -- (c) a pass: emulated profiles → decoder → tf → ProfileAssembler ----------------------------------------------

R_WS = np.array([[-1.0, 0, 0], [0, 1, 0], [0, 0, -1]])  # sensor x = world −X, y = +Y (travel), z = −Z (down)
R_FS = Rotation.from_euler("xyz", [3.0, -2.0, 35.0], degrees=True).as_matrix()  # hand-eye flange ← sensor
T_FS = np.array([0.012, -0.004, 0.061])
SPEED = 0.1  # m/s: 10 mm in 100 profiles at 1 kHz


def _sensor_origin(t_ns: np.ndarray) -> np.ndarray:
    s = (np.asarray(t_ns) - T0) * 1e-9
    return np.stack([np.full_like(s, 0.5), SPEED * s, np.full_like(s, 0.080)], axis=-1)  # 80 mm above z = 0


def _pass_buffer(sensor_frame: str) -> TransformBuffer:
    buf = TransformBuffer()
    buf.set_transform_arrays("flange", sensor_frame, [0], T_FS[None], Rotation.from_matrix(R_FS).as_quat()[None],
                             static=True)
    stamps = T0 + np.arange(0, 106, 2) * MS  # robot tf at 500 Hz, linear motion: interpolation is exact
    r_wf = R_WS @ R_FS.T
    p_wf = _sensor_origin(stamps) - (r_wf @ T_FS)[None]
    buf.set_transform_arrays("world", "flange", stamps, p_wf, np.repeat(Rotation.from_matrix(r_wf).as_quat()[None],
                                                                        len(stamps), axis=0))
    return buf


@pytest.mark.parametrize("name", NAMES)
def test_a_pass_assembles_to_the_points_computed_in_the_fixed_frame(name):
    h, w = 100, 2048
    stamps = T0 + 500_000 + np.arange(h) * MS  # 1 kHz, between the tf samples, whole microseconds
    emus = [DRIVERS[name].builder(plane_profile(w, invalid=_mask(w, seed=i, frac=0.05)), int(s))
            for i, s in enumerate(stamps)]
    frame = emus[0].msg.header.frame_id
    asm = ProfileAssembler(_pass_buffer(frame), "world", ScanTrigger("count", count=h))
    scans = []
    for e in emus:
        scans += asm.add(profile_from_cloud(e.msg, **e.decode_kwargs))
    assert len(scans) == 1 and asm.counters.balanced
    scan = scans[0]
    assert scan.end is ScanEnd.COUNT and scan.sensor_frame == frame and scan.points.shape[0] == h
    assert np.array_equal(scan.stamps_ns, stamps)
    width = max(e.points.shape[0] for e in emus)
    assert scan.points.shape == (h, width, 3)
    exact = np.full((h, width, 3), np.nan)  # the directly computed fixed-frame points, mm
    ideal = np.full((h, width, 3), np.nan)  # the same from the unrounded plane (float64 geometry)
    origins = _sensor_origin(stamps)
    for i, e in enumerate(emus):
        n = e.points.shape[0]
        exact[i, :n] = (e.points @ R_WS.T + origins[i]) * 1000.0
        cols = e.columns if e.columns is not None else np.arange(n)
        ideal[i, :n] = (plane_profile(w)[cols] @ R_WS.T + origins[i]) * 1000.0
        ideal[i, :n][~np.isfinite(e.points).all(axis=1)] = np.nan
    valid = np.isfinite(exact).all(axis=2)
    assert np.array_equal(scan.valid, valid)
    assert np.isnan(scan.points[~valid]).all()  # no-returns stay NaN in their row position
    np.testing.assert_allclose(scan.points[valid], exact[valid], rtol=0, atol=1e-9 * 1000)
    np.testing.assert_allclose(scan.points[valid], ideal[valid], rtol=0, atol=1e-5)  # float32 rounding of ≤ 0.08 m
    assert np.allclose(scan.points[valid][:, 2], 0.0, atol=1e-5)  # on the plane
    travelled = scan.sensor_poses[-1, :3, 3] - scan.sensor_poses[0, :3, 3]
    np.testing.assert_allclose(travelled, [0.0, 9.9, 0.0], atol=1e-9)  # mm, 99 intervals of 1 ms at 0.1 m/s
    if name in DROPPING:
        # Dropped no-returns lose their column: each row holds its returns compacted, NaN-padded at the end.
        assert np.array_equal(scan.widths, [e.points.shape[0] for e in emus]) and (scan.widths < w).all()
        for i in range(h):
            assert valid[i, : scan.widths[i]].all() and not valid[i, scan.widths[i]:].any()
    else:
        assert (scan.widths == w).all()
        holes = np.stack([_mask(w, seed=i, frac=0.05) for i in range(h)])
        if name == "scancontrol_samxl":
            holes[:, -2:] = True
        assert np.array_equal(~valid, holes)  # the holes where the sensor had them
    for k in emus[0].fields:
        stacked = np.full((h, width), np.nan)
        for i, e in enumerate(emus):
            stacked[i, : e.fields[k].shape[0]] = e.fields[k]
        np.testing.assert_array_equal(scan.fields[k], stacked)


# -- (d) organized clouds through cloud_to_scan -------------------------------------------------------------------

def _organized(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    y = np.arange(h)[:, None] * 1e-4 * np.ones((1, w))
    x = np.linspace(-0.03, 0.03, w)[None] * np.ones((h, 1))
    z = 0.3 + 0.01 * np.sin(x * 50) + 0.001 * y
    pts = np.stack([x, y, z], axis=-1)
    pts[rng.random((h, w)) < 0.08] = np.nan
    pts[10:14, 20:40] = np.nan  # a hole
    return pts


@pytest.mark.parametrize("name", sorted(ORGANIZED))
def test_organized_clouds_go_through_cloud_to_scan_with_their_holes(name):
    h, w = 60, 128
    e = ORGANIZED[name].builder(_organized(h, w, seed=5), T0)
    assert e.msg.height == h and e.msg.width == w and not e.msg.is_dense
    validate_cloud(e.msg)
    scan = cloud_to_scan(e.msg, ScanSettings(10.0, 4.0, 0.5), HeadPose.looking_down(), "emulated")
    assert scan.organized and scan.shape == (h, w) and scan.frame_id == e.msg.header.frame_id
    np.testing.assert_array_equal(scan.points, e.points * 1000.0)  # mm, NaN holes kept in place
    holes = ~np.isfinite(e.points).all(axis=2)
    assert holes[10:14, 20:40].all() and np.isnan(scan.points[holes]).all() and np.isfinite(scan.points[~holes]).all()
    assert set(scan.fields) == set(e.fields)
    for k, v in e.fields.items():
        np.testing.assert_array_equal(scan.fields[k], v)
    with pytest.raises(CloudFormatError, match="organized"):
        profile_from_cloud(e.msg)  # a batch is not one profile
