"""The node's two output clouds, built byte by byte into buffers the messages adopt (no extra copies).

- ``~/deviations``: one record per (kept) input point, x, y, z as received and the predicted deviation dx, dy, dz
  (d = measured − nominal, ``scan.targets.published_deviation`` of the model's target), dnorm, their expanded
  uncertainty (95 %) ux, uy, uz (float32, metres), flags (uint16), 2 bytes of padding:
  point_step 44, every field at an offset aligned to its size in every point;
- ``~/cad_deviations`` (with a CAD part configured): one record per judged point, x, y, z as received, the signed
  deviation measured − CAD along its outward normal ``before`` and ``after`` the compensation, ``u_normal`` (U
  carried onto the normal), float32 metres, ``index`` (uint32: the point's flat index in ``~/deviations``), flags
  (uint16), 2 bytes of padding: point_step 32;
- ``~/corrected``: the input cloud (same fields, byte order and point layout) with x, y, z − d (measured minus
  the predicted deviation); the residual uncertainty of each corrected coordinate is U (ux, uy, uz of
  ``~/deviations``).

Frames: the input cloud's (``header.frame_id``); lengths in metres as on every topic.
"""

from __future__ import annotations

import array
import sys
from typing import Any

import numpy as np
from numba import njit, prange
from sensor_msgs.msg import PointCloud2, PointField

from ..compute import threads as _threads  # noqa: F401 - the threading layer, before any parallel kernel runs
from .cloud import dtype_from_fields, new_cloud_message
from .convert import M_PER_MM, mm_to_m

__all__ = ["CAD_FIELDS", "CAD_POINT_STEP", "DEVIATIONS_FIELDS", "DEVIATIONS_POINT_STEP", "cad_cloud", "corrected_cloud",
           "deviations_cloud", "warm_up"]


#: ``~/deviations`` point layout: (name, offset, PointField datatype); point_step :data:`DEVIATIONS_POINT_STEP`.
DEVIATIONS_FIELDS = (("x", 0, PointField.FLOAT32), ("y", 4, PointField.FLOAT32), ("z", 8, PointField.FLOAT32),
                     ("dx", 12, PointField.FLOAT32), ("dy", 16, PointField.FLOAT32), ("dz", 20, PointField.FLOAT32),
                     ("dnorm", 24, PointField.FLOAT32), ("ux", 28, PointField.FLOAT32), ("uy", 32, PointField.FLOAT32),
                     ("uz", 36, PointField.FLOAT32), ("flags", 40, PointField.UINT16))
DEVIATIONS_POINT_STEP = 44


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def _fill_deviations(rec: np.ndarray, rec16: np.ndarray, points_m: np.ndarray, dev_mm: np.ndarray,
                     unc_mm: np.ndarray, has_unc: bool, flags: np.ndarray, negate: bool) -> None:
    """One pass over the 44-byte records (``rec`` their float32 view (N, 11), ``rec16`` their uint16 view (N, 22)):
    the float operations of the numpy version, in its order — metres = float32(mm × 1e-3), dnorm = float32 sqrt of
    ((dx² + dy²) + dz²) in float32 — so the bytes are the same. ``negate``: write −d (NaN kept as it is: the
    published deviation from the model's target, :func:`xmetro_ros.scan.targets.published_deviation`)."""
    nan32 = np.float32(np.nan)
    for i in prange(rec.shape[0]):
        acc = np.float32(0.0)
        for k in range(3):
            rec[i, k] = points_m[i, k]
            v = dev_mm[i, k]
            if negate and not np.isnan(v):
                v = -v
            d = np.float32(v * 1e-3)
            rec[i, 3 + k] = d
            acc += d * d
            rec[i, 7 + k] = np.float32(unc_mm[i, k] * 1e-3) if has_unc else nan32
        rec[i, 6] = np.sqrt(acc)
        rec16[i, 20] = flags[i]


def warm_up() -> None:
    """Compile (or load from numba's cache) the record kernel now, not on the first scan."""
    rec = np.zeros((1, DEVIATIONS_POINT_STEP // 4), np.float32)
    for neg in (False, True):
        _fill_deviations(rec, rec.view(np.uint16), np.zeros((1, 3), np.float32), np.zeros((1, 3)), np.zeros((1, 3)),
                         True, np.zeros(1, np.uint16), neg)
    recs = np.zeros((1, 4), np.float32)
    _shift_records(recs, recs, np.zeros(1, np.int64), False, np.zeros((1, 3)), 0)


def deviations_cloud(header: Any, points_m: np.ndarray, dev_mm: np.ndarray, flags: np.ndarray, height: int,
                     width: int, unc_mm: np.ndarray | None = None, from_target: bool = False) -> PointCloud2:
    """``~/deviations``: ``points_m`` (N, 3) float32 metres as received, ``dev_mm`` (N, 3) predicted deviation
    d = measured − nominal in mm (NaN where none), ``unc_mm`` (N, 3) its expanded uncertainty U (95 %) in mm
    (NaN where none; None: all NaN), ``flags`` (N,) uint16; ``height × width = N``. Layout
    :data:`DEVIATIONS_FIELDS`, 44 bytes a point. ``from_target``: ``dev_mm`` is the model's target t = nominal −
    measured and d = −t is written (the same bytes as passing ``published_deviation(dev_mm)``, without its copy)."""
    n = int(height) * int(width)
    if points_m.shape[0] != n or dev_mm.shape[0] != n or flags.shape[0] != n:
        raise ValueError(f"height {height} × width {width} != {points_m.shape[0]} points")
    fields = [PointField(name=name, offset=off, datatype=code, count=1) for name, off, code in DEVIATIONS_FIELDS]
    data = array.array("B", b"\0") * (n * DEVIATIONS_POINT_STEP)  # zeroed: the padding bytes are 0
    if n:
        # One compiled pass over the records (per-field strided numpy writes took ~17 ms on 167k points).
        rec = np.frombuffer(data, dtype=np.float32).reshape(n, DEVIATIONS_POINT_STEP // 4)
        rec16 = np.frombuffer(data, dtype=np.uint16).reshape(n, DEVIATIONS_POINT_STEP // 2)
        unc = np.zeros((1, 3)) if unc_mm is None else np.ascontiguousarray(unc_mm, dtype=np.float64)
        _fill_deviations(rec, rec16, np.ascontiguousarray(points_m, dtype=np.float32),
                         np.ascontiguousarray(dev_mm, dtype=np.float64), unc, unc_mm is not None,
                         np.ascontiguousarray(flags, dtype=np.uint16), bool(from_target))
        del rec, rec16
    cloud = new_cloud_message(header=header, height=int(height), width=int(width),
                              is_dense=False,
                              is_bigendian=sys.byteorder == "big", fields=fields,
                              point_step=DEVIATIONS_POINT_STEP, row_step=DEVIATIONS_POINT_STEP * int(width))
    cloud.data = data
    return cloud


#: ``~/cad_deviations`` point layout; point_step :data:`CAD_POINT_STEP`.
CAD_FIELDS = (("x", 0, PointField.FLOAT32), ("y", 4, PointField.FLOAT32), ("z", 8, PointField.FLOAT32),
              ("before", 12, PointField.FLOAT32), ("after", 16, PointField.FLOAT32),
              ("u_normal", 20, PointField.FLOAT32), ("index", 24, PointField.UINT32), ("flags", 28, PointField.UINT16))
CAD_POINT_STEP = 32


def cad_cloud(header: Any, points_m: np.ndarray, index: np.ndarray, before_mm: np.ndarray, after_mm: np.ndarray,
              u_normal_mm: np.ndarray, flags: np.ndarray) -> PointCloud2:
    """``~/cad_deviations``: one record per judged point (an unorganized 1 × N cloud): ``points_m`` (N, 3) float32
    metres as received, the deviations from the CAD along its normal ``before`` / ``after`` the compensation and
    ``u_normal`` (N,) mm, ``index`` (N,) flat indices into ``~/deviations``, ``flags`` (N,) uint16."""
    n = len(index)
    if not (points_m.shape[0] == len(before_mm) == len(after_mm) == len(u_normal_mm) == len(flags) == n):
        raise ValueError("cad_cloud: every per-point array needs the same length")
    fields = [PointField(name=name, offset=off, datatype=code, count=1) for name, off, code in CAD_FIELDS]
    data = array.array("B", b"\0") * (n * CAD_POINT_STEP)
    if n:
        view = np.frombuffer(data, dtype=dtype_from_fields(fields, CAD_POINT_STEP), count=n)
        for k, name in enumerate("xyz"):
            view[name] = points_m[:, k]
        view["before"] = mm_to_m(np.asarray(before_mm, np.float64))
        view["after"] = mm_to_m(np.asarray(after_mm, np.float64))
        view["u_normal"] = mm_to_m(np.asarray(u_normal_mm, np.float64))
        view["index"] = index
        view["flags"] = flags
        del view
    cloud = new_cloud_message(header=header, height=1, width=n, is_dense=False,
                              is_bigendian=sys.byteorder == "big", fields=fields, point_step=CAD_POINT_STEP,
                              row_step=CAD_POINT_STEP * n)
    cloud.data = data
    return cloud


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def _shift_records(rec: np.ndarray, src: np.ndarray, keep: np.ndarray, use_keep: bool, target_mm: np.ndarray,
                   c: int) -> None:
    """rec[r] = src[keep[r]] (src[r] without ``use_keep``), then its float32 x, y, z (columns c..c+2) + the shift
    float32(t) × float32(1e-3), 0 where not finite — numpy's ``astype`` / multiply / mask / ``+=``, in float32, so the
    bytes are the goldens'."""
    m = np.float32(M_PER_MM)
    z = np.float32(0.0)
    for r in prange(rec.shape[0]):
        s = keep[r] if use_keep else np.int64(r)
        for j in range(rec.shape[1]):
            rec[r, j] = src[s, j]
        for k in range(3):
            sh = np.float32(target_mm[r, k]) * m
            if not np.isfinite(sh):
                sh = z
            rec[r, c + k] = rec[r, c + k] + sh


def corrected_cloud(msg: PointCloud2, target_mm: np.ndarray, keep: np.ndarray | None, height: int,
                    width: int) -> PointCloud2:
    """The input cloud (same fields and byte order) with x, y, z + t, t the model's target (nominal − measured):
    x, y, z − d for the published deviation d = −t; unpredicted points unchanged.

    Args:
        msg: the input cloud (already validated).
        target_mm: (N, 3) the model's predicted target t = nominal − measured, mm, one row per kept point (NaN
            where none).
        keep: indices of the kept input points (decimated scans), None for all.
        height, width: shape of the output (``height × width = N``).
    """
    by = {f.name: f for f in msg.fields}
    ps = int(msg.point_step)
    fx = by["x"]
    n_out = height * width
    # The message's own array('B') buffer, filled once (assigning bytes would make the message copy them again).
    buf = array.array("B", b"\0") * (n_out * ps)
    fast = (not msg.is_bigendian and sys.byteorder == "little" and ps % 4 == 0 and fx.offset % 4 == 0
            and all(by[a].datatype == PointField.FLOAT32 for a in "xyz")
            and by["y"].offset == fx.offset + 4 and by["z"].offset == fx.offset + 8
            and int(msg.row_step) == ps * int(msg.width))
    if fast and n_out:
        # The common case (our own clouds): one compiled pass copies the (kept) records into the buffer and adjusts
        # x, y, z there.
        src = np.frombuffer(msg.data, dtype=np.float32).reshape(-1, ps // 4)
        rec = np.frombuffer(buf, dtype=np.float32).reshape(n_out, ps // 4)
        idx = np.zeros(0, np.int64) if keep is None else np.ascontiguousarray(keep, dtype=np.int64)
        _shift_records(rec, src, idx, keep is not None, np.ascontiguousarray(target_mm, dtype=np.float64),
                       fx.offset // 4)
        del rec
    elif n_out:
        # float32 arithmetic on purpose: the published clouds are float32 and must stay bit-identical to the goldens
        shift = target_mm.astype(np.float32) * np.float32(M_PER_MM)
        shift[~np.isfinite(shift)] = 0.0
        dt = dtype_from_fields(msg.fields, ps, is_bigendian=bool(msg.is_bigendian))
        raw: np.ndarray = np.ndarray(shape=(int(msg.height), int(msg.width)), dtype=dt, buffer=msg.data,
                                     strides=(int(msg.row_step), ps)).reshape(-1)
        recs: np.ndarray = raw[keep] if keep is not None else raw.copy()
        for i, axis in enumerate(("x", "y", "z")):
            recs[axis] = recs[axis] + shift[:, i].astype(recs[axis].dtype)
        np.frombuffer(buf, dtype=np.uint8)[:] = np.ascontiguousarray(recs).reshape(-1).view(np.uint8)
    out = new_cloud_message()  # adopts buf without a copy
    out.header = msg.header
    out.height, out.width = height, width
    out.fields = list(msg.fields)
    out.is_bigendian = bool(msg.is_bigendian)
    out.point_step = int(msg.point_step)
    out.row_step = int(msg.point_step) * width
    out.is_dense = False
    out.data = buf
    return out
