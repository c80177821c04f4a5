"""The compiled single-pose geometry (scan/geometry_kernels.py, behind ``point_geometry``) gives, bit for bit and in
the same float types, what the numpy expressions it replaced gave (kept below as the reference): straight and turned
poses, float32 and float64 outputs, float32 and float64 points, the camera at the laser's height or offset, a point
on the laser's axis (zero distance), at 1 and at every thread."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from xmetro_ros.compute.threads import max_threads
from xmetro_ros.scan.geometry import HeadPose, camera_vector, point_geometry, rotation_xyz


def reference(points, pose, camera_mm, dtype=np.float64):
    """``point_geometry`` as it was in numpy (column-wise arithmetic), verbatim but for the returned tuple."""
    pts = np.asarray(points)
    r = pose.rotation
    d = np.ascontiguousarray((pts - pose.position).T, dtype=dtype)
    identity = bool(np.array_equal(r, np.eye(3)))
    if identity:
        x, y, z = d
    else:
        x, y, z = (r[0, j] * d[0] + r[1, j] * d[1] + r[2, j] * d[2] for j in range(3))
    xz2 = x * x + z * z
    dist = np.sqrt(xz2)
    inv_s = np.divide(1.0, dist, out=np.zeros_like(dist), where=dist > 0)
    cx, cy, cz = camera_vector(camera_mm)
    if cx == 0.0 and cz == 0.0:
        tx, tz, dcam = -x, -z, np.sqrt(xz2 + cy * cy)
    else:
        tx, tz = cx - x, cz - z
        dcam = np.sqrt(tx * tx + tz * tz + cy * cy)
    inv_c = np.divide(1.0, dcam, out=np.zeros_like(dcam), where=dcam > 0)
    lh = (-x * inv_s, np.zeros_like(x), -z * inv_s)
    vh = (tx * inv_c, cy * inv_c, tz * inv_c)
    L = np.empty((len(x), 3), dtype=x.dtype)
    V = np.empty((len(x), 3), dtype=x.dtype)
    for k in range(3):
        if identity:
            L[:, k], V[:, k] = lh[k], vh[k]
        else:
            L[:, k] = r[k, 0] * lh[0] + r[k, 2] * lh[2]
            V[:, k] = r[k, 0] * vh[0] + r[k, 1] * vh[1] + r[k, 2] * vh[2]
    return {"L": L, "V": V, "source_distance": dist, "standoff": -z, "u": x, "s": y}


POSES = {
    "straight": HeadPose(position=np.array([1.5, -20.0, 150.0]), rotation=np.eye(3)),
    "turned": HeadPose(position=np.array([1.5, -20.0, 150.0]), rotation=rotation_xyz(0.2, -0.35, 0.1)),
}


@pytest.mark.parametrize("pose", sorted(POSES))
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("points_dtype", [np.float32, np.float64])
@pytest.mark.parametrize("camera", [70.0, (12.0, 70.0, -4.0)])
def test_compiled_geometry_is_the_numpy_one(pose, dtype, points_dtype, camera):
    rng = np.random.default_rng(4)
    p = POSES[pose]
    pts = (rng.normal(0.0, 15.0, size=(20_001, 3)) + np.array([0.0, 0.0, 60.0])).astype(points_dtype)
    pts[7] = p.position + p.rotation @ np.array([0.0, 3.0, 0.0])  # on the laser's axis: zero source distance
    want = reference(pts, p, camera, dtype)
    before = numba.get_num_threads()
    try:
        for t in sorted({1, max_threads()}):
            numba.set_num_threads(t)
            got = point_geometry(pts, p, camera, dtype=dtype)
            for k, w in want.items():
                g = getattr(got, k)
                assert g.dtype == w.dtype, (k, g.dtype, w.dtype)
                np.testing.assert_array_equal(g, w, err_msg=f"{k} at {t} threads")
    finally:
        numba.set_num_threads(before)
