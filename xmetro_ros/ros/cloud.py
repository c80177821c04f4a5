"""sensor_msgs/PointCloud2 ⇄ numpy, without copies where the layout allows it.

Two layers:

- A drop-in replacement of ``sensor_msgs_py.point_cloud2`` (not available from pip): :func:`read_points`,
  :func:`read_points_numpy`, :func:`read_points_list`, :func:`create_cloud`, :func:`create_cloud_xyz32`,
  :func:`dtype_from_fields` with the same signatures, so code written for it runs on this module. Deliberate
  differences (all fixes of upstream defects, documented in docs/dds.md):

  * big-endian data is decoded through a big-endian dtype; the message buffer is never modified (upstream swaps the
    bytes of ``cloud.data`` in place, so reading a cloud twice gives garbage);
  * organized clouds follow upstream ((width, height) reshape); keyword ``row_major=True`` gives (height, width);
  * rows padded beyond ``width * point_step`` (``row_step`` larger) are read correctly;
  * malformed clouds raise :class:`CloudFormatError` (a ``ValueError`` and ``AssertionError``) with a code, never a
    numpy error or ``KeyError``; every layout check is O(fields) and runs before any allocation (docs/dds.md).

- Fast paths for the node: :func:`xyz_fields` returns x, y, z as an (N, 3) float array (a view of the message
  buffer when x, y, z are consecutive floats of native byte order, as in every cloud we publish) plus named extra
  fields as float arrays; :func:`create_cloud_from_arrays` packs named arrays into a cloud with one copy;
  :func:`validate_cloud` checks a received cloud and raises :class:`CloudFormatError` whose ``code`` is the name of
  a ``ScanQuality.ERROR_*`` constant.

Units are whatever the cloud carries (metres on ROS topics); nothing here converts units (see ros.convert).
NaN handling: NaN/Inf values are returned as they are (organized clouds keep their NaN placeholders);
``skip_nans=True`` drops points with a NaN in any returned field, as upstream.
"""

from __future__ import annotations

import array
import itertools
import sys
from collections import namedtuple
from collections.abc import Iterable, Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
from numpy.lib.recfunctions import structured_to_unstructured, unstructured_to_structured
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

__all__ = [
    "DUMMY_FIELD_PREFIX",
    "NP_TO_FIELD_TYPE",
    "CloudFormatError",
    "create_cloud",
    "create_cloud_from_arrays",
    "create_cloud_xyz32",
    "dtype_from_fields",
    "field_names",
    "fields_to_dtype",
    "new_cloud_message",
    "read_points",
    "read_points_list",
    "read_points_numpy",
    "validate_cloud",
    "xyz_fields",
]


def new_cloud_message(**fields: Any) -> PointCloud2:
    """A PointCloud2 whose ``data`` setter adopts an ``array.array('B')`` as is.

    Only a message created with ``check_fields=True`` does: with field checks off (rosidl's default) the generated
    setter copies the whole buffer again (~3 ms per 6 MB cloud). The checks on the few scalar fields cost
    microseconds. Every cloud this package builds goes through here.
    """
    return PointCloud2(check_fields=True, **fields)


_DATATYPES: dict[int, np.dtype] = {
    PointField.INT8: np.dtype(np.int8),
    PointField.UINT8: np.dtype(np.uint8),
    PointField.INT16: np.dtype(np.int16),
    PointField.UINT16: np.dtype(np.uint16),
    PointField.INT32: np.dtype(np.int32),
    PointField.UINT32: np.dtype(np.uint32),
    PointField.FLOAT32: np.dtype(np.float32),
    PointField.FLOAT64: np.dtype(np.float64),
}
#: numpy scalar type → PointField datatype (as upstream).
NP_TO_FIELD_TYPE: dict[Any, int] = {dt.type: code for code, dt in _DATATYPES.items()}
DUMMY_FIELD_PREFIX = "unnamed_field"
_FLOAT_TYPES = (PointField.FLOAT32, PointField.FLOAT64)
_NATIVE_BIG = sys.byteorder == "big"


class CloudFormatError(ValueError, AssertionError):
    """A PointCloud2 that cannot be read as a scan.

    A ``ValueError``, and an ``AssertionError`` too: sensor_msgs_py signals the same conditions (count 0, duplicate
    names, a requested field absent) with ``assert``, so code written for it that catches those still does.

    Attributes:
        code: name of the matching ``ScanQuality.ERROR_*`` constant without the prefix: ``EMPTY_CLOUD``,
            ``BAD_LAYOUT`` (data length, row_step, point_step, offsets, count or datatype inconsistent),
            ``MISSING_FIELD`` (x, y or z missing or not floating point), ``DUPLICATE_FIELD``, ``NO_VALID_POINTS``
            (every point has a NaN/Inf coordinate), ``MISSING_INPUT_FIELD`` (a requested extra field is absent).
    """

    CODES = ("EMPTY_CLOUD", "BAD_LAYOUT", "MISSING_FIELD", "DUPLICATE_FIELD", "NO_VALID_POINTS", "MISSING_INPUT_FIELD")

    def __init__(self, code: str, message: str) -> None:
        if code not in self.CODES:
            raise ValueError(f"unknown cloud error code {code!r}")
        super().__init__(message)
        self.code = code

    @property
    def error_code(self) -> int:
        """The numeric ``ScanQuality.ERROR_*`` value of :attr:`code`."""
        from ..msg import ScanQuality

        return int(getattr(ScanQuality, f"ERROR_{self.code}"))


class CloudArgumentError(ValueError, AssertionError):
    """An argument of the sensor_msgs_py API that cannot be used (mixed datatypes where one is needed, an array whose
    dtype does not match the fields). An ``AssertionError`` too, as sensor_msgs_py raises those with ``assert``."""


# --------------------------------------------------------------------------------------------------------------
# layout checks (no expansion of count > 1 fields, nothing allocated in proportion to claimed sizes)

#: numpy keeps a dtype's itemsize and field offsets in a C int: larger point_step / offsets cannot be described.
_MAX_ITEMSIZE = 2**31 - 1


class _Field(NamedTuple):
    """One PointField after the checks: its column name (unnamed → ``unnamed_field_<i>``), dtype in data byte order."""

    name: str
    offset: int
    dtype: np.dtype
    count: int  # type: ignore[assignment]  # the PointField's count, shadowing tuple.count on purpose

    @property
    def end(self) -> int:
        return self.offset + self.count * self.dtype.itemsize

    def sub_names(self) -> list[str]:
        """Column names of the field: itself, or ``name_0 .. name_<count-1>`` (as sensor_msgs_py)."""
        return [self.name] if self.count == 1 else [f"{self.name}_{a}" for a in range(self.count)]


def _check_fields(
    fields: Iterable[Any], point_step: int | None, order: str, *, forbid_overlap: bool
) -> list[_Field]:
    """Checked fields in message order; O(F log F) whatever the counts (count > 1 fields are never expanded here).

    Checks: known datatype, count ≥ 1, every field (all its elements) inside ``point_step`` (or inside numpy's C-int
    itemsize when ``point_step`` is None), optionally no two fields overlapping, and unique column names after the
    count > 1 expansion, decided without expanding it.
    """
    out: list[_Field] = []
    for i, f in enumerate(fields):
        name = f.name or f"{DUMMY_FIELD_PREFIX}_{i}"
        try:
            dt = _DATATYPES[int(f.datatype)]
        except KeyError:
            raise CloudFormatError(
                "BAD_LAYOUT", f"field {name!r} has unknown PointField datatype {f.datatype}"
            ) from None
        count = int(f.count)
        if count < 1:
            raise CloudFormatError("BAD_LAYOUT", f"field {name!r} has count {count}")
        out.append(_Field(name, int(f.offset), dt.newbyteorder(order), count))  # type: ignore[arg-type]
    limit = _MAX_ITEMSIZE if point_step is None else int(point_step)
    if limit > _MAX_ITEMSIZE:
        raise CloudFormatError("BAD_LAYOUT", f"point_step {limit} exceeds {_MAX_ITEMSIZE} bytes")
    end = max((f.end for f in out), default=0)
    if end > limit:
        if point_step is None:
            raise CloudFormatError("BAD_LAYOUT", f"fields end at byte {end}, beyond numpy's {_MAX_ITEMSIZE}")
        raise CloudFormatError("BAD_LAYOUT", f"point_step {limit} is smaller than its fields ({end} bytes)")
    if forbid_overlap:
        spans = sorted((f.offset, f.end) for f in out)
        for (_a0, a1), (b0, _b1) in itertools.pairwise(spans):
            if b0 < a1:
                raise CloudFormatError("BAD_LAYOUT", f"fields overlap at byte offset {b0}")
    _check_unique_names(out)
    return out


def _check_unique_names(fields: Sequence[_Field]) -> None:
    """Raise DUPLICATE_FIELD when two column names would coincide after the count > 1 expansion; O(F).

    ``name_k`` (k written in decimal, as the expansion does) is split at its last underscore, so a single name
    collides with a count > 1 field exactly when it is ``<that field's name>_<k>`` with k < count, and two count > 1
    fields collide exactly when they share a name.
    """
    singles: set[str] = set()
    multis: dict[str, int] = {}
    for f in fields:
        if f.count == 1:
            if f.name in singles:
                raise CloudFormatError("DUPLICATE_FIELD", f"duplicate field name {f.name!r}")
            singles.add(f.name)
        else:
            if f.name in multis:
                raise CloudFormatError("DUPLICATE_FIELD", f"duplicate field name {f.name + '_0'!r}")
            multis[f.name] = f.count
    if not multis:
        return
    for s in singles:
        base, sep, k = s.rpartition("_")
        # ≤ 10 digits: indices of a uint32 count (and int() of a 5000-digit string would raise)
        if sep and base in multis and 0 < len(k) <= 10 and k.isascii() and k.isdigit() and (k == "0" or k[0] != "0"):
            if int(k) < multis[base]:
                raise CloudFormatError("DUPLICATE_FIELD", f"duplicate field name {s!r}")


def _structured_dtype(fields: Sequence[_Field], point_step: int | None) -> np.dtype:
    """Structured dtype of checked fields (count > 1 expanded: O(total count), bounded by the checks)."""
    names: list[str] = []
    offsets: list[int] = []
    formats: list[np.dtype] = []
    for f in fields:
        size = f.dtype.itemsize
        names.extend(f.sub_names())
        offsets.extend(range(f.offset, f.offset + f.count * size, size))
        formats.extend([f.dtype] * f.count)
    spec: dict[str, Any] = {"names": names, "formats": formats, "offsets": offsets}
    if point_step is not None:
        spec["itemsize"] = int(point_step)
    return np.dtype(spec)  # type: ignore[call-overload]  # numpy's stub lacks the dict form of a dtype


def dtype_from_fields(
    fields: Iterable[Any], point_step: int | None = None, *, is_bigendian: bool | None = None
) -> np.dtype:
    """Structured numpy dtype of one point described by ``fields`` (as sensor_msgs_py).

    Fields with ``count > 1`` become sub-fields ``<name>_0 .. <name>_<count-1>``; unnamed fields become
    ``unnamed_field_<i>``. Every check runs on the field list before the expansion (O(F log F)); the expansion
    itself is linear in the total count, which ``point_step`` bounds when given.

    Args:
        fields: PointField messages (anything with name, offset, datatype, count).
        point_step: itemsize of the dtype (bytes per point); default: packed up to the end of the last field.
        is_bigendian: byte order of the data; None (upstream behaviour) = native.

    Raises:
        CloudFormatError: unknown datatype, count 0, a field beyond ``point_step`` or ``point_step`` ≥ 2³¹
            (``BAD_LAYOUT``), duplicate names (``DUPLICATE_FIELD``).
    """
    order = "=" if is_bigendian is None else (">" if is_bigendian else "<")
    return _structured_dtype(_check_fields(fields, point_step, order, forbid_overlap=False), point_step)


def fields_to_dtype(fields: Iterable[Any], point_step: int | None = None) -> np.dtype:
    """Alias of :func:`dtype_from_fields` (the ros_numpy name)."""
    return dtype_from_fields(fields, point_step)


def field_names(cloud: PointCloud2) -> list[str]:
    """Names of the columns :func:`read_points` returns (count > 1 fields expanded to ``name_i``)."""
    fields = _check_fields(cloud.fields, None, "=", forbid_overlap=False)
    return [name for f in fields for name in f.sub_names()]


# --------------------------------------------------------------------------------------------------------------
# validation and raw views


def _check_layout(cloud: PointCloud2) -> list[_Field]:
    """Check sizes, offsets and names of a non-empty cloud; return its checked fields (data byte order).

    O(F log F) integer arithmetic on the header and the field list, in an order such that nothing is built from a
    claimed size before the claims are checked against ``len(data)``: after these checks every field, expanded or
    not, lies inside one point, ``point_step`` × width inside ``row_step`` and ``row_step`` × height is the data.
    """
    height, width = int(cloud.height), int(cloud.width)
    if height * width == 0:
        raise CloudFormatError("EMPTY_CLOUD", f"cloud has no points (width {width}, height {height})")
    if not cloud.fields:
        raise CloudFormatError("BAD_LAYOUT", "cloud has no fields")
    point_step, row_step, size = int(cloud.point_step), int(cloud.row_step), len(cloud.data)
    if point_step == 0:
        raise CloudFormatError("BAD_LAYOUT", "point_step is 0")
    if point_step > _MAX_ITEMSIZE:
        raise CloudFormatError("BAD_LAYOUT", f"point_step {point_step} exceeds {_MAX_ITEMSIZE} bytes")
    packed_row = width * point_step
    if row_step < packed_row:
        raise CloudFormatError("BAD_LAYOUT", f"row_step {row_step} is smaller than width × point_step = {packed_row}")
    expected = row_step * height
    if size != expected:
        raise CloudFormatError(
            "BAD_LAYOUT",
            f"data has {size} bytes, expected {expected} "
            f"(height {height} × row_step {row_step}; width {width}, point_step {point_step})",
        )
    order = ">" if cloud.is_bigendian else "<"
    return _check_fields(cloud.fields, point_step, order, forbid_overlap=True)


def _raw_points(cloud: PointCloud2, dtype: np.dtype) -> np.ndarray:
    """(H, W) structured view of the buffer honouring row_step (no copy)."""
    return np.ndarray(
        shape=(int(cloud.height), int(cloud.width)),
        dtype=dtype,
        buffer=cloud.data,
        strides=(int(cloud.row_step), int(cloud.point_step)),
    )


def _column(cloud: PointCloud2, f: _Field, index: int | None = None) -> np.ndarray:
    """Values of one checked field as (N,) — or (N, count) for a count > 1 field without ``index`` — in data byte
    order: a strided view of the buffer (a copy only when padded rows make a flat view impossible)."""
    h, w = int(cloud.height), int(cloud.width)
    size = f.dtype.itemsize
    whole = f.count > 1 and index is None
    a: np.ndarray = np.ndarray(
        shape=(h, w, f.count) if whole else (h, w),
        dtype=f.dtype,
        buffer=cloud.data,
        offset=f.offset + (index or 0) * size,
        strides=(int(cloud.row_step), int(cloud.point_step), size) if whole else (int(cloud.row_step),
                                                                                  int(cloud.point_step)),
    )
    return a.reshape(h * w, f.count) if whole else a.reshape(h * w)


def validate_cloud(cloud: PointCloud2, *, require_valid_points: bool = True) -> None:
    """Check that ``cloud`` can be read as a scan; raise :class:`CloudFormatError` (with ``.code``) otherwise.

    Checked, in this order and before anything is allocated (O(F log F) for the layout): points present; point_step
    > 0 and < 2³¹ (numpy's limit); row_step ≥ width × point_step; data length = height × row_step; known datatypes,
    count ≥ 1, every field inside point_step, no overlapping fields; unique names (after the count > 1 expansion,
    decided without expanding); x, y, z present and floating point (float32 or float64, either endianness:
    big-endian clouds are valid and decoded by the readers); with ``require_valid_points`` (O(N)), at least one
    point whose x, y, z are all finite (``NO_VALID_POINTS`` otherwise). Finite values are never judged here, however
    large (3e38 is a valid float32): the node's working volume does that.
    """
    fields = _check_layout(cloud)
    _xyz_fields_of(fields)
    if require_valid_points:
        xyz, _ = xyz_fields(cloud, _checked_fields=fields)
        # x + y + z is finite iff all three are, bar float overflow (huge finite values), which the second test
        # settles; the sum is 30x faster than isfinite(...).all(axis=1) on the strided view of a 180k-point cloud.
        with np.errstate(over="ignore", invalid="ignore"):
            finite_sum = np.isfinite(xyz[:, 0] + xyz[:, 1] + xyz[:, 2]).any()
        if not finite_sum and not np.isfinite(xyz).all(axis=1).any():
            raise CloudFormatError("NO_VALID_POINTS", f"all {len(xyz)} points have a NaN or Inf coordinate")


def _xyz_fields_of(fields: Sequence[_Field]) -> tuple[_Field, _Field, _Field]:
    """The x, y, z columns: fields of count 1 (a count > 1 field ``x`` is the columns x_0.., which may coexist)."""
    singles = {f.name: f for f in fields if f.count == 1}
    multis = {f.name: f for f in fields if f.count > 1}
    out = []
    for axis in ("x", "y", "z"):
        f = singles.get(axis, multis.get(axis))
        if f is None:
            names = [f.name for f in fields]
            raise CloudFormatError("MISSING_FIELD", f"cloud has no {axis!r} field (fields: {names})")
        if f.dtype.kind != "f" or f.count != 1:
            raise CloudFormatError(
                "MISSING_FIELD", f"field {axis!r} must be one float32/float64 value, got {f.dtype.name} count {f.count}"
            )
        out.append(f)
    return out[0], out[1], out[2]


# --------------------------------------------------------------------------------------------------------------
# sensor_msgs_py.point_cloud2 API


def _organize(points: np.ndarray, cloud: PointCloud2, row_major: bool) -> np.ndarray:
    """sensor_msgs_py's shape (width, height) of the row-major point sequence, or (height, width) with row_major."""
    h, w = int(cloud.height), int(cloud.width)
    return points.reshape((h, w) if row_major else (w, h))


def read_points(
    cloud: PointCloud2,
    field_names: list[str] | None = None,
    skip_nans: bool = False,
    uvs: Iterable | None = None,
    reshape_organized_cloud: bool = False,
    *,
    row_major: bool = False,
) -> np.ndarray:
    """Read points from a PointCloud2 as a structured array (one column per field / sub-field).

    Zero-copy (a view of ``cloud.data``) for little-endian clouds without row padding; big-endian clouds are
    converted to native byte order (one copy; the message is left untouched) and padded rows are compacted.

    Args:
        cloud: the cloud.
        field_names: fields to read (None: all).
        skip_nans: drop points with a NaN in any selected field (only when ``cloud.is_dense`` is false, as upstream).
        uvs: flat indices of the points to return.
        reshape_organized_cloud: when height > 1, return the points (in data order) reshaped to
            ``(width, height)``, as sensor_msgs_py does (its create_cloud writes a (W, H) array that way, so the two
            round-trip); with ``row_major=True``, ``(height, width)``: row r = the r-th row of the image (REP 118).
        row_major: see ``reshape_organized_cloud`` (keyword only; not in sensor_msgs_py).

    Raises:
        CloudFormatError: malformed layout, or a requested field is absent (``MISSING_INPUT_FIELD``).
    """
    if not isinstance(cloud, PointCloud2):
        raise TypeError("cloud is not a sensor_msgs.msg.PointCloud2")
    if int(cloud.width) * int(cloud.height) == 0:
        # No data bounds the claims of an empty cloud: the fields are checked (O(F)) but expanded only when each
        # sub-field can have a byte of its own in a point of ≤ 2^16 bytes; anything larger reads as unreadable.
        fields = _check_fields(cloud.fields, cloud.point_step, "=", forbid_overlap=True)
        if int(cloud.point_step) > 1 << 16:
            raise CloudFormatError("BAD_LAYOUT", f"empty cloud with point_step {cloud.point_step} > 65536")
        return np.zeros(0, dtype=_structured_dtype(fields, cloud.point_step))
    fields = _check_layout(cloud)
    points = _raw_points(cloud, _structured_dtype(fields, int(cloud.point_step)))
    if field_names is not None:
        names = set(points.dtype.names)
        missing = [f for f in field_names if f not in names]
        if missing:
            raise CloudFormatError("MISSING_INPUT_FIELD", f"fields {missing} are not in the cloud {list(names)}")
        points = points[list(field_names)]
    points = points.reshape(-1)  # a view unless rows are padded
    if bool(cloud.is_bigendian) != _NATIVE_BIG:
        points = points.astype(points.dtype.newbyteorder("="))
    if skip_nans and not cloud.is_dense:
        keep = np.ones(len(points), dtype=bool)
        for name in points.dtype.names or ():
            if points.dtype[name].kind == "f":
                keep &= ~np.isnan(points[name])
        points = points[keep]
    if uvs is not None:
        if not isinstance(uvs, np.ndarray):
            uvs = np.fromiter(uvs, int)
        points = points[uvs]
    if reshape_organized_cloud and cloud.height > 1:
        points = _organize(points, cloud, row_major)
    return points


def read_points_numpy(
    cloud: PointCloud2,
    field_names: list[str] | None = None,
    skip_nans: bool = False,
    uvs: Iterable | None = None,
    reshape_organized_cloud: bool = False,
    *,
    row_major: bool = False,
) -> np.ndarray:
    """Read equally typed fields as an unstructured (N, F) array (a view when the fields are evenly spaced).

    Raises:
        CloudArgumentError: the selected fields do not all have the same datatype (use :func:`read_points`); a
            ``ValueError`` and an ``AssertionError`` (sensor_msgs_py asserts).
        CloudFormatError: as :func:`read_points`.
    """
    if not isinstance(cloud, PointCloud2):
        raise TypeError("cloud is not a sensor_msgs.msg.PointCloud2")
    # Checked on the field list first, as upstream: O(F), before anything is read.
    selected = cloud.fields if field_names is None else [f for f in cloud.fields if f.name in set(field_names)]
    if len({int(f.datatype) for f in selected}) > 1:
        raise CloudArgumentError("All fields need to have the same datatype. Use `read_points()` otherwise.")
    points = read_points(cloud, field_names, skip_nans, uvs, reshape_organized_cloud, row_major=row_major)
    if len({points.dtype.fields[k][0] for k in points.dtype.names}) > 1:  # sub-field names (``normal_1``) selected
        raise CloudArgumentError("All fields need to have the same datatype. Use `read_points()` otherwise.")
    return structured_to_unstructured(points)


def read_points_list(
    cloud: PointCloud2,
    field_names: list[str] | None = None,
    skip_nans: bool = False,
    uvs: Iterable | None = None,
) -> list[NamedTuple]:
    """Read points as a list of namedtuples ``Point(<field>=value, ...)`` (slow; for small clouds and tests)."""
    points = read_points(cloud, field_names, skip_nans, uvs)
    Point = namedtuple("Point", points.dtype.names)  # type: ignore[misc]
    return [Point._make(p) for p in points.tolist()]


def _cloud_from_structured(header: Header, fields: Sequence[Any], points: np.ndarray, row_major: bool) -> PointCloud2:
    if points.ndim > 2:
        raise CloudArgumentError(f"points can have at most 2 dimensions (organized cloud), got shape {points.shape}")
    if points.ndim == 1:
        height, width = 1, points.shape[0]
    elif row_major:
        height, width = points.shape[0], points.shape[1]
    else:  # sensor_msgs_py: a (A, B) array is width A, height B, written in its memory order
        height, width = points.shape[1], points.shape[0]
    points = np.ascontiguousarray(points)
    data = array.array("B")
    data.frombytes(points.reshape(-1).view(np.uint8).data)
    cloud = new_cloud_message(
        header=header,
        height=height,
        width=width,
        is_dense=False,
        is_bigendian=_NATIVE_BIG,
        fields=list(fields),
        point_step=points.dtype.itemsize,
        row_step=points.dtype.itemsize * width,
    )
    cloud.data = data  # set after construction: adopted as is (new_cloud_message; ros2/common_interfaces#176)
    return cloud


def create_cloud(
    header: Header,
    fields: Iterable[Any],
    points: Any,
    point_step: int | None = None,
    *,
    row_major: bool = False,
) -> PointCloud2:
    """Create a PointCloud2 (as sensor_msgs_py).

    Args:
        header: header of the cloud.
        fields: PointField list describing one point.
        points: a structured array with the fields of ``fields``, an unstructured (N, F) / (A, B, F) array (all
            fields of one datatype), or an iterable of per-point sequences (slow). A 2-D structured / 3-D
            unstructured array of shape (A, B) gives an organized cloud written in memory order with width A and
            height B, as sensor_msgs_py (:func:`read_points` reshapes it back); ``row_major=True``: height A, width B
            (REP 118 image order).
        point_step: bytes per point; default: packed (end of the last field). A structured array must have exactly
            the dtype :func:`dtype_from_fields` gives for ``fields`` and ``point_step`` (itemsize included).
        row_major: see ``points`` (keyword only; not in sensor_msgs_py).

    Raises:
        CloudArgumentError: mixed datatypes with an unstructured array, a structured array whose fields or itemsize
            differ from ``fields`` / ``point_step``, more than 2 point dimensions.
        CloudFormatError: invalid ``fields`` (as :func:`dtype_from_fields`).
    """
    fields = list(fields)
    dtype = dtype_from_fields(fields, point_step)
    if isinstance(points, np.ndarray):
        if points.dtype.names is None:
            if any(f.datatype != fields[0].datatype for f in fields[1:]):
                raise CloudArgumentError(
                    "All fields need to have the same datatype. Pass a structured array otherwise.")
            points = unstructured_to_structured(points, dtype=dtype)
        elif points.dtype != dtype:  # names, order, types, offsets and itemsize (= point_step or packed)
            raise CloudArgumentError(
                f"PointFields (point_step {point_step}) and structured array dtype {points.dtype} do not match "
                "(order, names, types, offsets, itemsize)"
            )
    else:
        points = np.array([tuple(p) for p in points], dtype=dtype)
    return _cloud_from_structured(header, fields, points, row_major)


def create_cloud_xyz32(header: Header, points: Any, *, row_major: bool = False) -> PointCloud2:
    """Create a PointCloud2 with float32 x, y, z fields from (N, 3) points (or (A, B, 3): see :func:`create_cloud`)."""
    fields = [
        PointField(name="x", offset=0, datatype=PointField.FLOAT32, count=1),
        PointField(name="y", offset=4, datatype=PointField.FLOAT32, count=1),
        PointField(name="z", offset=8, datatype=PointField.FLOAT32, count=1),
    ]
    if isinstance(points, np.ndarray) and points.dtype.names is None:
        points = points.astype(np.float32, copy=False)
    return create_cloud(header, fields, points, row_major=row_major)


# --------------------------------------------------------------------------------------------------------------
# fast paths


def _as_float(col: np.ndarray) -> np.ndarray:
    """Native-order float view of a column when possible, a float copy otherwise (ints → float64)."""
    if col.dtype.kind == "f":
        return col if col.dtype.isnative else col.astype(col.dtype.newbyteorder("="))
    return col.astype(np.float64)


def xyz_fields(
    cloud: PointCloud2, extra: Iterable[str] = (), *, _checked_fields: list[_Field] | None = None
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """x, y, z as an (N, 3) float array and the named extra fields as float arrays, in one call.

    N = height × width (organized clouds are flattened row-major; NaN placeholders kept). When x, y, z are
    consecutive float32 (or float64) values in native byte order and rows are not padded, ``xyz`` is a read-only-
    by-convention *view* of ``cloud.data`` (no copy, whatever other fields the point has); otherwise one copy.
    Extra float fields are strided views likewise; integer fields are converted to float64; an extra name may be a
    field with count > 1 (→ (N, count)) or one of its sub-fields ``name_i``. Values are returned as they are
    (NaN, Inf, and finite values of any size). Cost: the layout checks (O(F log F)) plus O(N) per returned column;
    no structured dtype is built and count > 1 fields are not expanded.

    Raises:
        CloudFormatError: malformed layout (``EMPTY_CLOUD``, ``BAD_LAYOUT``, ``DUPLICATE_FIELD``), x/y/z absent or
            not floating point (``MISSING_FIELD``), an extra field absent (``MISSING_INPUT_FIELD``).
    """
    fields = _checked_fields if _checked_fields is not None else _check_layout(cloud)
    fx, fy, fz = _xyz_fields_of(fields)
    n = int(cloud.height) * int(cloud.width)
    ft = fx.dtype
    contiguous = (
        fx.dtype == fy.dtype == fz.dtype
        and fy.offset == fx.offset + ft.itemsize
        and fz.offset == fx.offset + 2 * ft.itemsize
        and (cloud.height == 1 or cloud.row_step == cloud.width * cloud.point_step)
    )
    if contiguous:
        base: np.ndarray = np.ndarray(
            shape=(n, 3), dtype=ft, buffer=cloud.data, offset=fx.offset, strides=(int(cloud.point_step), ft.itemsize)
        )
        xyz = base if base.dtype.isnative else base.astype(ft.newbyteorder("="))
    else:
        xyz = np.empty((n, 3), dtype=np.result_type(*(f.dtype.newbyteorder("=") for f in (fx, fy, fz))))
        for i, f in enumerate((fx, fy, fz)):
            xyz[:, i] = _column(cloud, f)
    extras: dict[str, np.ndarray] = {}
    # Column names first (count-1 fields, then sub-fields name_k), then count > 1 fields by their own name; names
    # are unique as columns (checked), but a count > 1 field "a" may coexist with a column "a".
    singles = {f.name: f for f in fields if f.count == 1}
    multis = {f.name: f for f in fields if f.count > 1}
    for name in extra:
        fs = singles.get(name)
        if fs is not None:
            extras[name] = _as_float(_column(cloud, fs))
            continue
        base_name, _, k = name.rpartition("_")  # a sub-field name_k of a count > 1 field
        fm = multis.get(base_name)
        index = int(k) if 0 < len(k) <= 10 and k.isascii() and k.isdigit() else -1
        if fm is not None and f"{base_name}_{index}" == name and index < fm.count:
            extras[name] = _as_float(_column(cloud, fm, index))
            continue
        fw = multis.get(name)
        if fw is None:
            names = [g.name for g in fields]
            raise CloudFormatError("MISSING_INPUT_FIELD", f"cloud has no field {name!r} (fields: {names})")
        extras[name] = _as_float(_column(cloud, fw))  # (N, count)
    return xyz, extras


def _field_type_of(name: str, dt: np.dtype) -> tuple[np.dtype, int]:
    if dt == np.bool_:
        dt = np.dtype(np.uint8)
    dt = dt.newbyteorder("=")
    if dt.type not in NP_TO_FIELD_TYPE:
        raise ValueError(f"field {name!r}: dtype {dt} has no PointField datatype (use int8..uint32, float32/64)")
    return dt, NP_TO_FIELD_TYPE[dt.type]


def create_cloud_from_arrays(
    header: Header,
    arrays: Mapping[str, np.ndarray],
    height: int | None = None,
    width: int | None = None,
    *,
    is_dense: bool | None = None,
    point_step: int | None = None,
) -> PointCloud2:
    """Pack named per-point arrays into a PointCloud2 (fields in the mapping's order, packed, native byte order).

    Args:
        header: header of the cloud.
        arrays: name → array of shape (N,) or (N, k) (k > 1 → one field with count k), or (H, W) / (H, W, k) for
            an organized cloud (a 3-D array sets H, W when not given; with H, W given, arrays whose leading shape
            is (H, W) are flattened row-major). The dtype of each array is kept (bool → uint8); int64, float16
            etc. are refused.
        height, width: cloud shape; default from the arrays ((H, W) leading shape) or height 1, width N.
        is_dense: default: true when every float value is finite.
        point_step: bytes per point, >= the packed size (None: packed); the padding bytes are zero.

    Raises:
        ValueError: empty mapping, inconsistent lengths, unsupported dtype, height × width ≠ N.
    """
    if not arrays:
        raise ValueError("create_cloud_from_arrays needs at least one array")
    shapes = [np.shape(a) for a in arrays.values()]
    if height is None and width is None and any(len(sh) == 3 for sh in shapes):
        height, width = shapes[0][0], shapes[0][1]
    n = None
    cols: list[tuple[str, np.ndarray, np.dtype, int, int]] = []
    fields = []
    offset = 0
    for name, a in arrays.items():
        a = np.asarray(a)
        if height is not None and width is not None and a.ndim in (2, 3) and a.shape[:2] == (height, width):
            a = a.reshape(a.shape[0] * a.shape[1], *a.shape[2:])
        if a.ndim not in (1, 2):
            raise ValueError(f"field {name!r}: expected shape (N,) or (N, k), got {a.shape}")
        count = 1 if a.ndim == 1 else a.shape[1]
        if n is None:
            n = a.shape[0]
        elif a.shape[0] != n:
            raise ValueError(f"field {name!r} has {a.shape[0]} points, expected {n}")
        dt, code = _field_type_of(name, a.dtype)
        fields.append(PointField(name=name, offset=offset, datatype=code, count=count))
        cols.append((name, a, dt, count, offset))
        offset += dt.itemsize * count
    assert n is not None
    if height is None and width is None:
        height, width = 1, n
    elif height is None:
        height = n // int(width) if width else 0
    elif width is None:
        width = n // int(height) if height else 0
    assert height is not None and width is not None
    if int(height) * int(width) != n:
        raise ValueError(f"height {height} × width {width} != {n} points")
    if point_step is None:
        point_step = offset
    elif point_step < offset:
        raise ValueError(f"point_step {point_step} < packed size {offset}")
    dtype = dtype_from_fields(fields, point_step)
    data = array.array("B", b"\0") * (n * point_step)
    if n:
        # Fill the message's own buffer through a structured view: one copy per field, no intermediate bytes.
        view = np.frombuffer(data, dtype=dtype, count=n)
        for name, a, _dt, count, _off in cols:
            if count == 1:
                view[name] = a
            else:
                for k in range(count):
                    view[f"{name}_{k}"] = a[:, k]
        del view
    if is_dense is None:
        is_dense = all(np.isfinite(a).all() for _, a, dt, _, _ in cols if dt.kind == "f")
    cloud = new_cloud_message(
        header=header,
        height=int(height),
        width=int(width),
        is_dense=bool(is_dense),
        is_bigendian=_NATIVE_BIG,
        fields=fields,
        point_step=point_step,
        row_step=point_step * int(width),
    )
    cloud.data = data
    return cloud
