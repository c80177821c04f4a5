"""The ROS-free transform buffer (xmetro_ros/scan/tf_buffer.py): interpolation exact at samples and midpoints
(translation lerp, rotation SLERP against scipy's Slerp), chained lookups through static and dynamic edges equal
to the matrix product, every error code in its case, the extrapolation bound, the bounded history, batch lookups."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation, Slerp

from xmetro_ros.scan.tf_buffer import (
    TfErrorCode,
    TransformBuffer,
    TransformError,
    TransformRecord,
    invert_transforms,
    matrices_to_quats,
    quats_to_matrices,
)

MS = 1_000_000  # ns


def _t(rot: Rotation, p) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = rot.as_matrix()
    out[:3, 3] = p
    return out


def _rec(stamp, parent, child, rot: Rotation, p) -> TransformRecord:
    q = rot.as_quat()  # scipy: (x, y, z, w), the ROS order
    return TransformRecord(int(stamp), parent, child, tuple(map(float, p)), tuple(map(float, q)))


quat_st = st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 0.1)
vec_st = st.lists(st.floats(-2, 2, allow_nan=False), min_size=3, max_size=3)


# -- quaternion helpers -------------------------------------------------------------------------------------------

@settings(max_examples=60, deadline=None)
@given(q=quat_st)
def test_quaternion_matrix_round_trip_matches_scipy(q):
    r = Rotation.from_quat(q)
    m = quats_to_matrices(np.array([q]))[0]
    np.testing.assert_allclose(m, r.as_matrix(), atol=1e-12)
    back = matrices_to_quats(m[None])[0]
    assert back[3] >= 0
    np.testing.assert_allclose(np.abs(back @ r.as_quat()), 1.0, atol=1e-12)


def test_invert_transforms():
    t = _t(Rotation.from_euler("xyz", [10, -20, 30], degrees=True), [1, 2, 3])
    np.testing.assert_allclose(invert_transforms(t[None])[0] @ t, np.eye(4), atol=1e-14)


# -- interpolation ------------------------------------------------------------------------------------------------

@settings(max_examples=60, deadline=None)
@given(q0=quat_st, q1=quat_st, p0=vec_st, p1=vec_st, u=st.floats(0, 1), dt_ms=st.integers(1, 500))
def test_interpolation_is_lerp_and_slerp(q0, q1, p0, p1, u, dt_ms):
    buf = TransformBuffer()
    r0, r1 = Rotation.from_quat(q0), Rotation.from_quat(q1)
    t0, t1 = 1_000 * MS, (1_000 + dt_ms) * MS
    buf.set_transform(_rec(t0, "a", "b", r0, p0))
    buf.set_transform(_rec(t1, "a", "b", r1, p1))
    # exact at the samples
    for t, r, p in ((t0, r0, p0), (t1, r1, p1)):
        m = buf.lookup("a", "b", t)
        np.testing.assert_array_equal(m[:3, 3], np.asarray(p, dtype=float))
        np.testing.assert_allclose(m[:3, :3], r.as_matrix(), atol=1e-12)
    # between them: translation linear, rotation along the shorter arc (scipy's Slerp is the reference)
    t = t0 + round(u * (t1 - t0))
    uu = (t - t0) / (t1 - t0)
    m = buf.lookup("a", "b", t)
    np.testing.assert_allclose(m[:3, 3], (1 - uu) * np.asarray(p0) + uu * np.asarray(p1), atol=1e-12)
    ref = Slerp([0.0, 1.0], Rotation.concatenate([r0, r1]))([uu])[0]
    np.testing.assert_allclose(m[:3, :3], ref.as_matrix(), atol=1e-9)


def test_midpoint_of_a_known_rotation():
    buf = TransformBuffer()
    buf.set_transform(_rec(0, "a", "b", Rotation.identity(), [0, 0, 0]))
    buf.set_transform(_rec(10 * MS, "a", "b", Rotation.from_euler("z", 90, degrees=True), [2, 0, 0]))
    m = buf.lookup("a", "b", 5 * MS)
    np.testing.assert_allclose(m[:3, :3], Rotation.from_euler("z", 45, degrees=True).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(m[:3, 3], [1, 0, 0], atol=0)


def test_samples_out_of_order_are_sorted_and_repeats_ignored():
    buf = TransformBuffer()
    for s, x in ((20, 2.0), (0, 0.0), (10, 1.0), (10, 99.0)):
        buf.set_transform(_rec(s * MS, "a", "b", Rotation.identity(), [x, 0, 0]))
    assert buf.stats["stored"] == 3 and buf.stats["ignored"] == 1
    assert buf.lookup("a", "b", 15 * MS)[0, 3] == pytest.approx(1.5)


# -- chains -------------------------------------------------------------------------------------------------------

def _robot(rng: np.random.Generator) -> tuple[TransformBuffer, dict[str, object]]:
    """world → base (static) → link (dynamic) → flange (dynamic) → sensor (static); world → fixture (static)."""
    buf = TransformBuffer()
    rnd_rot = lambda: Rotation.from_rotvec(rng.normal(size=3))  # noqa: E731
    statics = {"base": ("world", rnd_rot(), rng.normal(size=3)), "sensor": ("flange", rnd_rot(), rng.normal(size=3)),
               "fixture": ("world", rnd_rot(), rng.normal(size=3))}
    for child, (parent, r, p) in statics.items():
        buf.set_transform(_rec(0, parent, child, r, p), static=True)
    stamps = np.arange(0, 101) * 10 * MS
    dyn = {}
    for child, parent in (("link", "base"), ("flange", "link")):
        rots = Rotation.from_rotvec(rng.normal(size=(len(stamps), 3)) * 0.3)
        trans = rng.normal(size=(len(stamps), 3))
        buf.set_transform_arrays(parent, child, stamps, trans, rots.as_quat())
        dyn[child] = (stamps, rots, trans)
    return buf, {"statics": statics, "dyn": dyn}


def _edge_at(info, child, t) -> np.ndarray:
    if child in info["statics"]:
        _, r, p = info["statics"][child]
        return _t(r, p)
    stamps, rots, trans = info["dyn"][child]
    i = min(np.searchsorted(stamps, t, side="right") - 1, len(stamps) - 2)
    u = (t - stamps[i]) / (stamps[i + 1] - stamps[i])
    r = Slerp([0.0, 1.0], Rotation.concatenate([rots[i], rots[i + 1]]))([u])[0]
    return _t(r, (1 - u) * trans[i] + u * trans[i + 1])


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31), t=st.integers(0, 1000 * MS))
def test_chained_lookup_equals_the_matrix_product(seed, t):
    buf, info = _robot(np.random.default_rng(seed))
    e = lambda c: _edge_at(info, c, t)  # noqa: E731
    world_sensor = e("base") @ e("link") @ e("flange") @ e("sensor")
    want = np.linalg.inv(e("fixture")) @ world_sensor
    np.testing.assert_allclose(buf.lookup("fixture", "sensor", t), want, atol=1e-9)
    np.testing.assert_allclose(buf.lookup("sensor", "fixture", t), np.linalg.inv(want), atol=1e-9)
    np.testing.assert_allclose(buf.lookup("world", "sensor", t), world_sensor, atol=1e-9)
    np.testing.assert_allclose(buf.lookup("link", "sensor", t), e("flange") @ e("sensor"), atol=1e-9)
    np.testing.assert_allclose(buf.lookup("sensor", "sensor", t), np.eye(4))


def test_batch_lookup_equals_single_lookups_and_reports_per_stamp():
    buf, _ = _robot(np.random.default_rng(3))
    stamps = np.array([-5 * MS, 0, 333 * MS, 999 * MS, 1000 * MS, 1001 * MS])
    res = buf.lookup_batch("fixture", "sensor", stamps, raise_on_error=False)
    assert res.codes() == [TfErrorCode.EXTRAPOLATION_PAST, TfErrorCode.OK, TfErrorCode.OK, TfErrorCode.OK,
                           TfErrorCode.OK, TfErrorCode.EXTRAPOLATION_FUTURE]
    for i in np.flatnonzero(res.ok):
        np.testing.assert_array_equal(res.matrices[i], buf.lookup("fixture", "sensor", int(stamps[i])))
    assert np.all(np.isnan(res.matrices[~res.ok]))
    with pytest.raises(TransformError) as e:  # raising: the final (past) failure first
        buf.lookup_batch("fixture", "sensor", stamps)
    assert e.value.code is TfErrorCode.EXTRAPOLATION_PAST and e.value.stamp_ns == -5 * MS
    assert buf.time_range("fixture", "sensor") == (0, 1000 * MS)
    assert buf.lookup_batch("fixture", "sensor", []).matrices.shape == (0, 4, 4)


def test_static_only_path_answers_any_stamp_and_frames_lose_their_slash():
    buf = TransformBuffer()
    buf.set_transform(_rec(5, "/flange", "sensor", Rotation.from_euler("x", 180, degrees=True), [0, 0, 0.1]),
                      static=True)
    assert buf.can_transform("flange", "/sensor", -10**15) and buf.can_transform("flange", "sensor", 10**15)
    np.testing.assert_allclose(buf.lookup("sensor", "flange", 0)[:3, 3], [0, 0, 0.1], atol=1e-15)
    assert buf.frames == {"flange", "sensor"} and buf.parent_of("sensor") == "flange"


# -- errors -------------------------------------------------------------------------------------------------------

def _code(fn) -> TfErrorCode:
    with pytest.raises(TransformError) as e:
        fn()
    return e.value.code


def test_every_error_code_in_its_case():
    buf = TransformBuffer()
    buf.set_transform(_rec(0, "world", "base", Rotation.identity(), [0, 0, 0]), static=True)
    buf.set_transforms([_rec(s * MS, "base", "flange", Rotation.identity(), [s, 0, 0]) for s in (100, 110, 120)])
    buf.set_transform(_rec(0, "cart", "camera", Rotation.identity(), [0, 0, 0]), static=True)
    assert _code(lambda: buf.lookup("world", "nowhere", 110 * MS)) is TfErrorCode.UNKNOWN_FRAME
    assert _code(lambda: buf.lookup("world", "camera", 110 * MS)) is TfErrorCode.NOT_CONNECTED
    assert _code(lambda: buf.lookup("world", "flange", 121 * MS)) is TfErrorCode.EXTRAPOLATION_FUTURE
    assert _code(lambda: buf.lookup("world", "flange", 99 * MS)) is TfErrorCode.EXTRAPOLATION_PAST
    bad = [
        TransformRecord(0, "a", "b", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0)),  # zero quaternion
        TransformRecord(0, "a", "b", (np.nan, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
        TransformRecord(0, "a", "a", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
        TransformRecord(0, "", "b", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
        TransformRecord(0, "flange", "world", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),  # a loop
    ]
    for r in bad:
        assert _code(lambda r=r: buf.set_transform(r)) is TfErrorCode.INVALID_TRANSFORM
    assert buf.set_transforms(bad) == len(bad)
    assert buf.parent_of("world") is None  # the loop was not stored
    # asked without raising
    assert buf.check("world", "nowhere", 0) is TfErrorCode.UNKNOWN_FRAME
    assert buf.check("world", "camera", 0) is TfErrorCode.NOT_CONNECTED
    assert buf.check("world", "flange", 121 * MS) is TfErrorCode.EXTRAPOLATION_FUTURE
    assert buf.check("world", "flange", 99 * MS) is TfErrorCode.EXTRAPOLATION_PAST
    assert buf.check("world", "flange", 115 * MS) is TfErrorCode.OK
    assert [c.retryable for c in (TfErrorCode.UNKNOWN_FRAME, TfErrorCode.NOT_CONNECTED,
                                  TfErrorCode.EXTRAPOLATION_FUTURE, TfErrorCode.EXTRAPOLATION_PAST)] \
        == [True, True, True, False]


def test_late_tf_can_be_retried():
    buf = TransformBuffer()
    buf.set_transform(_rec(0, "w", "s", Rotation.identity(), [0, 0, 0]))
    buf.set_transform(_rec(10 * MS, "w", "s", Rotation.identity(), [1, 0, 0]))
    assert not buf.can_transform("w", "s", 15 * MS)
    v = buf.version
    buf.set_transform(_rec(20 * MS, "w", "s", Rotation.identity(), [2, 0, 0]))
    assert buf.version != v and buf.can_transform("w", "s", 15 * MS)
    assert buf.lookup("w", "s", 15 * MS)[0, 3] == pytest.approx(1.5)


def test_extrapolation_bound_is_respected_and_linear():
    buf = TransformBuffer(max_extrapolation_ns=5 * MS)
    rz = lambda d: Rotation.from_euler("z", d, degrees=True)  # noqa: E731
    buf.set_transform(_rec(100 * MS, "w", "s", rz(0), [0, 0, 0]))
    buf.set_transform(_rec(110 * MS, "w", "s", rz(10), [1, 0, 0]))
    m = buf.lookup("w", "s", 115 * MS)  # at the bound: extrapolated along the last segment
    np.testing.assert_allclose(m[:3, 3], [1.5, 0, 0], atol=1e-12)
    np.testing.assert_allclose(m[:3, :3], rz(15).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(buf.lookup("w", "s", 95 * MS)[:3, 3], [-0.5, 0, 0], atol=1e-12)
    assert buf.check("w", "s", 115 * MS + 1) is TfErrorCode.EXTRAPOLATION_FUTURE
    assert buf.check("w", "s", 95 * MS - 1) is TfErrorCode.EXTRAPOLATION_PAST
    # one sample: held within the bound, refused beyond it
    one = TransformBuffer(max_extrapolation_ns=2 * MS)
    one.set_transform(_rec(50 * MS, "w", "s", rz(0), [3, 0, 0]))
    assert one.lookup("w", "s", 52 * MS)[0, 3] == 3.0 and one.check("w", "s", 53 * MS) is not TfErrorCode.OK
    # the default bound is 0: never beyond the samples
    zero = TransformBuffer()
    zero.set_transform(_rec(50 * MS, "w", "s", rz(0), [3, 0, 0]))
    assert zero.can_transform("w", "s", 50 * MS) and not zero.can_transform("w", "s", 50 * MS + 1)


def test_history_is_bounded_per_edge():
    buf = TransformBuffer(cache_time_ns=1000 * MS)
    stamps = np.arange(0, 3001, 10) * MS  # 3 s at 100 Hz
    for s in stamps:
        buf.set_transform(_rec(s, "w", "s", Rotation.identity(), [s / 1e9, 0, 0]))
    assert buf.time_range("w", "s") == (2000 * MS, 3000 * MS)
    assert buf.check("w", "s", 1999 * MS) is TfErrorCode.EXTRAPOLATION_PAST
    before = buf.stats["ignored"]
    buf.set_transform(_rec(500 * MS, "w", "s", Rotation.identity(), [0, 0, 0]))  # older than the window: ignored
    assert buf.stats["ignored"] == before + 1 and buf.time_range("w", "s") == (2000 * MS, 3000 * MS)


def test_reparenting_replaces_the_edge_and_clear_forgets():
    buf = TransformBuffer()
    buf.set_transform(_rec(0, "a", "s", Rotation.identity(), [1, 0, 0]), static=True)
    buf.set_transform(_rec(0, "b", "s", Rotation.identity(), [2, 0, 0]), static=True)
    assert buf.parent_of("s") == "b" and buf.stats["reparented"] == 1
    assert buf.check("a", "s", 0) is TfErrorCode.UNKNOWN_FRAME  # "a" is named by no edge any more
    buf.clear()
    assert buf.check("b", "s", 0) is TfErrorCode.UNKNOWN_FRAME


def test_invalid_constructor_arguments():
    with pytest.raises(ValueError):
        TransformBuffer(cache_time_ns=0)
    with pytest.raises(ValueError):
        TransformBuffer(max_extrapolation_ns=-1)
