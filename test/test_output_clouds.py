"""The bytes of ``~/deviations`` (ros/output_clouds.py): the compiled one-pass record writer against a plain
structured-array build of the same layout (float32 metres = float32(mm × 1e-3), dnorm = float32 norm, flags at
offset 40, zero padding), fuzzed with hypothesis over sizes, NaN, huge values and absent U; and the cloud reads
back through the package's decoder."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from sensor_msgs.msg import PointField
from std_msgs.msg import Header

from xmetro_ros.ros.cloud import dtype_from_fields
from xmetro_ros.ros.node_outputs import cloud_arrays
from xmetro_ros.ros.output_clouds import DEVIATIONS_FIELDS, DEVIATIONS_POINT_STEP, deviations_cloud

FLOATS = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=64),
                   st.floats(-1e3, 1e3, allow_nan=False, width=64))


def reference_bytes(points_m: np.ndarray, dev_mm: np.ndarray, flags: np.ndarray, unc_mm: np.ndarray | None) -> bytes:
    """The layout written field by field with numpy (the writer the compiled pass replaced)."""
    n = len(points_m)
    fields = [PointField(name=name, offset=off, datatype=code, count=1) for name, off, code in DEVIATIONS_FIELDS]
    view = np.zeros(n, dtype=dtype_from_fields(fields, DEVIATIONS_POINT_STEP))
    dev_m = (np.asarray(dev_mm, np.float64) * 1e-3).astype(np.float32)
    u_m = np.full((n, 3), np.nan, np.float32) if unc_mm is None else (unc_mm * 1e-3).astype(np.float32)
    for k, name in enumerate("xyz"):
        view[name] = points_m[:, k]
        view["d" + name] = dev_m[:, k]
        view["u" + name] = u_m[:, k]
    with np.errstate(over="ignore", invalid="ignore"):
        view["dnorm"] = np.sqrt(np.einsum("ij,ij->i", dev_m, dev_m))
    view["flags"] = flags
    return view.tobytes()


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 40).flatmap(lambda n: st.tuples(
    hnp.arrays(np.float32, (n, 3), elements=st.floats(-10, 10, width=32)),
    hnp.arrays(np.float64, (n, 3), elements=FLOATS),
    hnp.arrays(np.uint16, (n,)),
    st.one_of(st.none(), hnp.arrays(np.float64, (n, 3), elements=FLOATS)))))
def test_deviation_records_are_the_reference_bytes(case) -> None:
    pts, dev, flags, unc = case
    with np.errstate(over="ignore", invalid="ignore"):
        want = reference_bytes(pts, dev, flags, unc)
        msg = deviations_cloud(Header(), pts, dev, flags, 1, len(pts), unc_mm=unc)
    assert bytes(msg.data) == want
    assert msg.point_step == DEVIATIONS_POINT_STEP and msg.row_step == DEVIATIONS_POINT_STEP * len(pts)


def test_large_cloud_reads_back() -> None:
    rng = np.random.default_rng(3)
    n = 50_000
    pts = rng.normal(0, 0.05, (n, 3)).astype(np.float32)
    dev = rng.normal(0, 0.02, (n, 3))
    dev[rng.random((n, 3)) < 0.02] = np.nan
    unc = np.abs(rng.normal(0, 0.03, (n, 3)))
    flags = rng.integers(0, 2048, n).astype(np.uint16)
    msg = deviations_cloud(Header(), pts, dev, flags, 250, 200, unc_mm=unc)
    assert bytes(msg.data) == reference_bytes(pts, dev, flags, unc)
    a = cloud_arrays(msg)
    np.testing.assert_array_equal(a["x"], pts[:, 0])
    np.testing.assert_array_equal(a["flags"], flags)
    np.testing.assert_array_equal(a["dz"], (dev[:, 2] * 1e-3).astype(np.float32))


def test_target_sign_flip_and_corrected_records_are_the_numpy_bytes() -> None:
    """``from_target`` writes the bytes of ``published_deviation(t)`` (−t, NaN kept); the compiled ``~/corrected``
    pass gives numpy's float32 ``astype`` / multiply / mask / ``+=`` bytes, with and without a kept subset."""
    from xmetro_ros.ros.convert import M_PER_MM, scan_to_cloud
    from xmetro_ros.ros.output_clouds import corrected_cloud
    from xmetro_ros.scan.artifacts import Sphere
    from xmetro_ros.scan.scanner import ScanSettings
    from xmetro_ros.scan.targets import published_deviation
    from xmetro_ros.sim import simulate_scan

    msg = scan_to_cloud(simulate_scan(Sphere(17.5, np.zeros(3)), ScanSettings(6.0, 3.0, 0.5), seed=1))
    n = msg.height * msg.width
    rng = np.random.default_rng(0)
    t = rng.normal(0, 0.05, (n, 3))
    t[rng.random((n, 3)) < 0.1] = np.nan
    t[5] = [-0.0, 0.0, np.inf]
    pts = rng.normal(0, 1, (n, 3)).astype(np.float32)
    flags = rng.integers(0, 2000, n).astype(np.uint16)
    a = deviations_cloud(Header(), pts, published_deviation(t), flags, msg.height, msg.width, unc_mm=np.abs(t))
    b = deviations_cloud(Header(), pts, t, flags, msg.height, msg.width, unc_mm=np.abs(t), from_target=True)
    assert bytes(a.data) == bytes(b.data)
    src = np.frombuffer(bytes(msg.data), dtype=np.float32).reshape(n, -1)
    c = next(f.offset for f in msg.fields if f.name == "x") // 4
    for keep in (None, np.sort(rng.choice(n, n // 3, replace=False))):
        tk = t if keep is None else t[keep]
        ref = (src if keep is None else src[keep]).copy()
        shift = tk.astype(np.float32) * np.float32(M_PER_MM)
        shift[~np.isfinite(shift)] = 0.0
        ref[:, c:c + 3] += shift
        h, w = (msg.height, msg.width) if keep is None else (1, len(keep))
        assert bytes(corrected_cloud(msg, tk, keep, h, w).data) == ref.tobytes()
