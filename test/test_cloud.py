"""xmetro_ros.ros.cloud against hand-built byte layouts (struct.pack): every datatype, padding, count > 1, big-endian,
organized clouds, NaN handling, validation codes and round trips."""

from __future__ import annotations

import array
import math
import struct

import numpy as np
import pytest
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from xmetro_ros.msg import ScanQuality
from xmetro_ros.ros import cloud as C

# (datatype, struct code, numpy dtype, sample value)
TYPES = [
    (PointField.INT8, "b", np.int8, -7),
    (PointField.UINT8, "B", np.uint8, 250),
    (PointField.INT16, "h", np.int16, -30000),
    (PointField.UINT16, "H", np.uint16, 65000),
    (PointField.INT32, "i", np.int32, -2_000_000_000),
    (PointField.UINT32, "I", np.uint32, 4_000_000_000),
    (PointField.FLOAT32, "f", np.float32, 1.5),
    (PointField.FLOAT64, "d", np.float64, -2.25e-3),
]


def make_cloud(fields, point_step, rows, *, width=None, height=1, row_step=None, bigendian=False, pad_row=0):
    """Cloud whose data is the concatenation of ``rows`` (bytes per point), ``pad_row`` zero bytes after each row."""
    width = len(rows) // height if width is None else width
    row_step = width * point_step + pad_row if row_step is None else row_step
    data = b""
    for r in range(height):
        data += b"".join(rows[r * width:(r + 1) * width]) + b"\0" * pad_row
    msg = PointCloud2(header=Header(frame_id="f"), height=height, width=width, fields=fields,
                      is_bigendian=bigendian, point_step=point_step, row_step=row_step, is_dense=False)
    msg.data = array.array("B", data)
    return msg


def pf(name, offset, datatype, count=1):
    return PointField(name=name, offset=offset, datatype=datatype, count=count)


def all_types_layout(order: str):
    """x, y, z float32 then one field of every datatype, each at a 1-byte-padded offset; point_step with tail pad."""
    fields = [pf("x", 0, PointField.FLOAT32), pf("y", 4, PointField.FLOAT32), pf("z", 8, PointField.FLOAT32)]
    fmt = order + "fff"
    off = 12
    for dt, code, npt, _ in TYPES:
        fmt += "x"  # one padding byte before every field
        off += 1
        fields.append(pf(f"f_{np.dtype(npt).name}", off, dt))
        fmt += code
        off += np.dtype(npt).itemsize
    fmt += "3x"
    point_step = off + 3
    assert struct.calcsize(fmt) == point_step
    return fields, fmt, point_step


@pytest.mark.parametrize("order", ["<", ">"])
def test_every_datatype_with_padding_either_endianness(order):
    fields, fmt, step = all_types_layout(order)
    values = [tuple([float(i), -float(i), 0.5 * i] + [v for *_, v in TYPES]) for i in range(4)]
    msg = make_cloud(fields, step, [struct.pack(fmt, *v) for v in values], bigendian=order == ">")
    before = bytes(msg.data)
    pts = C.read_points(msg)
    assert pts.dtype.isnative or all(pts.dtype[n].isnative for n in pts.dtype.names)
    assert pts.dtype.itemsize == step
    for i, v in enumerate(values):
        got = list(pts[i].tolist())
        assert got[:3] == list(v[:3])
        for (_dt, _code, npt, val), g in zip(TYPES, got[3:], strict=True):
            assert g == pytest.approx(val, rel=1e-7)
            assert pts.dtype[f"f_{np.dtype(npt).name}"] == np.dtype(npt)
    # the message is never modified (upstream byteswaps it in place), so a second read is identical
    assert bytes(msg.data) == before
    assert C.read_points(msg).tolist() == pts.tolist()
    C.validate_cloud(msg)
    xyz, ex = C.xyz_fields(msg, ["f_uint32", "f_float64", "f_int8"])
    np.testing.assert_array_equal(xyz, np.array([v[:3] for v in values], dtype=np.float32))
    assert ex["f_uint32"].dtype == np.float64 and ex["f_uint32"][0] == 4_000_000_000
    assert ex["f_int8"][2] == -7
    assert ex["f_float64"][3] == -2.25e-3


def test_count_greater_than_one_and_unnamed_field():
    fields = [pf("x", 0, PointField.FLOAT32), pf("y", 4, PointField.FLOAT32), pf("z", 8, PointField.FLOAT32),
              pf("normal", 12, PointField.FLOAT32, 3), pf("", 24, PointField.UINT16, 2)]
    fmt = "<ffffffHH"
    rows = [struct.pack(fmt, 1, 2, 3, 0.1, 0.2, 0.3, 7, 8), struct.pack(fmt, 4, 5, 6, -0.1, -0.2, -0.3, 9, 10)]
    msg = make_cloud(fields, 28, rows)
    pts = C.read_points(msg)
    assert pts.dtype.names == ("x", "y", "z", "normal_0", "normal_1", "normal_2", "unnamed_field_4_0",
                               "unnamed_field_4_1")
    assert pts["normal_1"].tolist() == pytest.approx([0.2, -0.2])
    assert pts["unnamed_field_4_1"].tolist() == [8, 10]
    _, ex = C.xyz_fields(msg, ["normal", "normal_2"])
    assert ex["normal"].shape == (2, 3)
    np.testing.assert_allclose(ex["normal"][1], [-0.1, -0.2, -0.3], rtol=1e-6)
    np.testing.assert_allclose(ex["normal_2"], [0.3, -0.3], rtol=1e-6)
    assert C.field_names(msg) == list(pts.dtype.names)
    normals = C.read_points_numpy(msg, ["normal_0", "normal_1", "normal_2"])
    assert normals.shape == (2, 3)


def test_organized_cloud_with_row_padding_and_nan():
    fields = [pf("z", 0, PointField.FLOAT64), pf("x", 8, PointField.FLOAT32), pf("y", 12, PointField.FLOAT32)]
    nan = math.nan
    vals = [(1.0, 0.0, 0.0), (2.0, 1.0, 0.0), (nan, nan, nan), (4.0, 0.0, 1.0), (5.0, 1.0, 1.0), (6.0, 2.0, 1.0)]
    rows = [struct.pack("<dff", *v) for v in vals]
    msg = make_cloud(fields, 16, rows, height=2, width=3, pad_row=8)
    assert msg.row_step == 56 and len(msg.data) == 112
    C.validate_cloud(msg)
    pts = C.read_points(msg, reshape_organized_cloud=True, row_major=True)
    assert pts.shape == (2, 3)
    assert pts["z"][1].tolist() == [4.0, 5.0, 6.0]
    assert math.isnan(pts["x"][0, 2])
    # sensor_msgs_py's order: the same point sequence as (width, height)
    up = C.read_points(msg, reshape_organized_cloud=True)
    assert up.shape == (3, 2) and up["z"].reshape(-1).tolist()[3:] == [4.0, 5.0, 6.0]
    flat = C.read_points(msg, ["x", "y", "z"], skip_nans=True)
    assert len(flat) == 5 and not np.isnan(flat["z"]).any()
    # xyz: non-contiguous layout → copied in x, y, z order, NaN kept, row padding skipped
    xyz, _ = C.xyz_fields(msg)
    assert xyz.shape == (6, 3)
    np.testing.assert_array_equal(xyz[[0, 1, 3, 4, 5]], [[0, 0, 1], [1, 0, 2], [0, 1, 4], [1, 1, 5], [2, 1, 6]])
    assert np.isnan(xyz[2]).all()
    sub = C.read_points(msg, uvs=[5, 0])
    assert sub["z"].tolist() == [6.0, 1.0]


def test_skip_nans_respects_is_dense_and_list_api():
    msg = C.create_cloud_xyz32(Header(), np.array([[0, 0, 0], [np.nan, 1, 1], [2, 2, 2]], dtype=np.float32))
    assert len(C.read_points(msg, skip_nans=True)) == 2
    msg.is_dense = True  # upstream semantics: a dense cloud is trusted
    assert len(C.read_points(msg, skip_nans=True)) == 3
    pts = C.read_points_list(msg, skip_nans=False)
    assert pts[2].x == 2.0 and pts[2]._fields == ("x", "y", "z")


def test_xyz_view_is_zero_copy():
    n = 1000
    arrays = {k: np.arange(n, dtype=np.float32) * (i + 1) for i, k in enumerate(["x", "y", "z", "intensity"])}
    arrays["line"] = np.arange(n, dtype=np.uint32)
    msg = C.create_cloud_from_arrays(Header(frame_id="m"), arrays)
    buf = np.frombuffer(msg.data, dtype=np.uint8)
    xyz, ex = C.xyz_fields(msg, ["intensity", "line"])
    assert np.shares_memory(xyz, buf) and np.shares_memory(ex["intensity"], buf)
    np.testing.assert_array_equal(xyz[:, 2], arrays["z"])
    np.testing.assert_array_equal(ex["line"], np.arange(n))
    assert np.shares_memory(C.read_points(msg), buf)
    assert np.shares_memory(C.read_points_numpy(msg, ["x", "y", "z"]), buf)


def test_create_cloud_round_trips():
    h = Header(frame_id="w")
    fields = [pf("x", 0, PointField.FLOAT32), pf("y", 4, PointField.FLOAT32), pf("z", 8, PointField.FLOAT32),
              pf("ring", 12, PointField.UINT16)]
    dt = C.dtype_from_fields(fields, 16)
    assert dt.itemsize == 16
    pts = np.zeros(5, dtype=dt)
    pts["x"] = np.arange(5)
    pts["ring"] = [1, 2, 3, 4, 5]
    msg = C.create_cloud(h, fields, pts, point_step=16)
    assert msg.point_step == 16 and msg.row_step == 80 and msg.width == 5 and msg.height == 1
    assert bytes(msg.data) == pts.tobytes()
    back = C.read_points(msg)
    assert back.dtype == dt and back.tolist() == pts.tolist()
    # python iterables (slow path) and organized (H, W) structured input
    msg2 = C.create_cloud(h, fields[:3], [(1, 2, 3), (4, 5, 6)])
    assert bytes(msg2.data) == struct.pack("<6f", 1, 2, 3, 4, 5, 6)
    org = C.create_cloud(h, fields, pts[:4].reshape(2, 2), point_step=16)
    assert (org.height, org.width) == (2, 2)
    assert C.read_points(org, reshape_organized_cloud=True)["ring"].tolist() == [[1, 2], [3, 4]]
    # unstructured (N, 3) input
    xyz = np.random.default_rng(0).normal(size=(7, 3)).astype(np.float32)
    np.testing.assert_array_equal(C.read_points_numpy(C.create_cloud_xyz32(h, xyz)), xyz)
    with pytest.raises(ValueError):
        C.create_cloud(h, fields, np.zeros((3, 4), np.float32))  # mixed datatypes need a structured array


def test_create_cloud_from_arrays_layout_and_organized():
    x = np.array([[1, 2], [3, 4]], dtype=np.float32)
    msg = C.create_cloud_from_arrays(Header(), {"x": x, "y": x, "z": x, "flag": np.ones((2, 2), bool),
                                                "n": np.zeros((2, 2, 3), np.float64)})
    assert (msg.height, msg.width, msg.point_step) == (2, 2, 12 + 1 + 24)
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields][3:] == [
        ("flag", 12, PointField.UINT8, 1), ("n", 13, PointField.FLOAT64, 3)]
    assert bytes(msg.data)[:12] == struct.pack("<3f", 1, 1, 1)
    assert msg.is_dense
    with pytest.raises(ValueError, match="int64"):
        C.create_cloud_from_arrays(Header(), {"x": np.zeros(3, np.int64)})
    with pytest.raises(ValueError, match="points"):
        C.create_cloud_from_arrays(Header(), {"x": np.zeros(3), "y": np.zeros(4)})
    with pytest.raises(ValueError):
        C.create_cloud_from_arrays(Header(), {"x": np.zeros(6)}, height=4, width=2)


def _xyz_msg(n=3):
    return C.create_cloud_xyz32(Header(), np.arange(3 * n, dtype=np.float32).reshape(n, 3))


def _bad(code, msg, **kw):
    with pytest.raises(C.CloudFormatError) as e:
        C.validate_cloud(msg, **kw)
    assert e.value.code == code, str(e.value)
    assert e.value.error_code == getattr(ScanQuality, f"ERROR_{code}")
    return e.value


def test_validate_cloud_codes():
    C.validate_cloud(_xyz_msg())
    m = _xyz_msg()
    m.width = 0
    _bad("EMPTY_CLOUD", m)
    m = _xyz_msg()
    m.data = array.array("B", bytes(m.data)[:-1])
    assert "expected 36" in str(_bad("BAD_LAYOUT", m))
    m = _xyz_msg()
    m.row_step = 20
    _bad("BAD_LAYOUT", m)
    m = _xyz_msg()  # larger row_step is fine when the data has it
    m.row_step, m.data = 40, array.array("B", bytes(m.data) + bytes(4))
    C.validate_cloud(m)
    m = _xyz_msg()
    m.point_step = 8
    m.row_step = 24
    m.data = array.array("B", bytes(24))
    assert "smaller than its fields" in str(_bad("BAD_LAYOUT", m))
    m = _xyz_msg()
    m.fields[2].offset = 6
    _bad("BAD_LAYOUT", m)  # overlapping
    m = _xyz_msg()
    m.fields[1].datatype = 9
    _bad("BAD_LAYOUT", m)
    m = _xyz_msg()
    m.fields = m.fields[:2]
    _bad("MISSING_FIELD", m)
    m = _xyz_msg()
    m.fields[2].datatype = PointField.INT32
    _bad("MISSING_FIELD", m)
    m = _xyz_msg()
    m.fields[1].name = "x"
    _bad("DUPLICATE_FIELD", m)
    m = C.create_cloud_xyz32(Header(), np.full((4, 3), np.nan, np.float32))
    _bad("NO_VALID_POINTS", m)
    C.validate_cloud(m, require_valid_points=False)
    m = C.create_cloud_xyz32(Header(), np.array([[np.inf, 0, 0], [0, np.nan, 0]], np.float32))
    _bad("NO_VALID_POINTS", m)
    with pytest.raises(C.CloudFormatError) as e:
        C.xyz_fields(_xyz_msg(), ["intensity"])
    assert e.value.code == "MISSING_INPUT_FIELD"
    with pytest.raises(C.CloudFormatError):
        C.read_points(_xyz_msg(), ["nope"])


def test_big_endian_float64_xyz_is_decoded():
    rows = [struct.pack(">ddd", 1.25, -2.5, 1e-3), struct.pack(">ddd", math.nan, 0.0, 3.0)]
    fields = [pf("x", 0, PointField.FLOAT64), pf("y", 8, PointField.FLOAT64), pf("z", 16, PointField.FLOAT64)]
    msg = make_cloud(fields, 24, rows, bigendian=True)
    C.validate_cloud(msg)
    xyz, _ = C.xyz_fields(msg)
    assert xyz.dtype == np.float64 and xyz.dtype.isnative
    np.testing.assert_array_equal(xyz[0], [1.25, -2.5, 1e-3])
    assert np.isnan(xyz[1, 0]) and xyz[1, 2] == 3.0
