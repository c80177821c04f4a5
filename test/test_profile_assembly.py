"""Profile assembly (xmetro_ros/scan/assembly.py): single profiles in the sensor frame + tf → organized scans in the
fixed frame. A synthetic pass (a sensor moving at constant speed over a sphere, the wrist turning 10° across the
pass, a hand-eye static transform) assembled from float32 sensor-frame profiles equals the points computed in the
fixed frame; rows keep their widths with NaN for no return; each trigger cuts where documented; out-of-order,
missing, unconnected, late and too-old profiles are counted with their reason; the held queue stays bounded."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from stream_rig import transform

from xmetro_ros.scan.assembly import (
    HEAD_IN_SENSOR,
    AssembledScan,
    DropReason,
    Profile,
    ProfileAssembler,
    ScanEnd,
    ScanTrigger,
)
from xmetro_ros.scan.geometry import HeadPose
from xmetro_ros.scan.tf_buffer import TransformBuffer

MS = 1_000_000  # ns
CENTRE, RADIUS = np.array([0.6, 0.1, 0.0]), 0.05  # the sphere, world frame, m


@dataclass
class Rig:
    """world → base (static) → flange (dynamic, from the robot) → sensor (static hand-eye).

    The flange translates along world +Y at ``speed`` m/s (standing still during ``stops``, [t0, t1) ms) and its
    wrist turns about its own x axis by ``wrist_deg`` over ``duration_ms``: both linear in time between the tf
    samples (every ``tf_ms``), so interpolating the samples is exact and the analytic pose is the ground truth.
    The sensor starts 0.3 m above the sphere's equator plane at y = 0, looking down (sensor z = world −z).
    """

    duration_ms: int = 1000
    speed: float = 0.2
    wrist_deg: float = 10.0
    tf_ms: int = 4
    stops: list[tuple[int, int]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.r_wb, self.t_wb = Rotation.from_euler("z", 30, degrees=True).as_matrix(), np.array([0.2, -0.1, 0.0])
        self.r_fs, self.t_fs = Rotation.from_euler("y", 2, degrees=True).as_matrix(), np.array([0.01, 0.0, 0.05])
        r_down = Rotation.from_euler("x", 180, degrees=True).as_matrix()
        self.r_bf0 = self.r_wb.T @ r_down @ self.r_fs.T
        self.p_bf0 = self.r_wb.T @ (np.array([0.6, 0.0, 0.3]) - self.t_wb) - self.r_bf0 @ self.t_fs
        self.dir_b = self.r_wb.T @ np.array([0.0, 1.0, 0.0])

    def travelled(self, t_ns: int) -> float:
        t_ms = t_ns / MS
        still = sum(max(0.0, min(t_ms, b) - a) for a, b in self.stops)
        return self.speed * (t_ms - still) / 1000.0

    def flange(self, t_ns: int) -> np.ndarray:
        theta = self.wrist_deg * t_ns / (self.duration_ms * MS)
        r = self.r_bf0 @ Rotation.from_euler("x", theta, degrees=True).as_matrix()
        return transform(r, self.p_bf0 + self.dir_b * self.travelled(t_ns))

    def world_sensor(self, t_ns: int) -> np.ndarray:
        return transform(self.r_wb, self.t_wb) @ self.flange(t_ns) @ transform(self.r_fs, self.t_fs)

    def feed_static(self, buf: TransformBuffer) -> None:
        for parent, child, r, p in (("world", "base", self.r_wb, self.t_wb),
                                    ("flange", "sensor", self.r_fs, self.t_fs)):
            q = Rotation.from_matrix(r).as_quat()
            buf.set_transform_arrays(parent, child, [0], p[None], q[None], static=True)

    def tf_stamps(self, until_ms: int | None = None) -> np.ndarray:
        return np.arange(0, (until_ms if until_ms is not None else self.duration_ms + self.tf_ms) + 1, self.tf_ms) * MS

    def feed_dynamic(self, buf: TransformBuffer, stamps: np.ndarray) -> None:
        mats = np.stack([self.flange(int(s)) for s in stamps])
        quats = Rotation.from_matrix(mats[:, :3, :3]).as_quat()
        buf.set_transform_arrays("base", "flange", stamps, mats[:, :3, 3], quats)

    def buffer(self, until_ms: int | None = None, **kw) -> TransformBuffer:
        buf = TransformBuffer(**kw)
        self.feed_static(buf)
        self.feed_dynamic(buf, self.tf_stamps(until_ms))
        return buf

    def profile(self, t_ns: int, width: int = 121, fan_deg: float = 15.0) -> tuple[Profile, np.ndarray]:
        """The profile at ``t_ns`` (float32 sensor-frame points, +inf where the ray misses the sphere) and the exact
        hits in the world frame (m; NaN for a miss)."""
        t = self.world_sensor(t_ns)
        a = np.radians(np.linspace(-fan_deg, fan_deg, width))
        d_s = np.stack([np.sin(a), np.zeros_like(a), np.cos(a)], axis=1)
        o, d = t[:3, 3], d_s @ t[:3, :3].T
        b = d @ (o - CENTRE)
        disc = b * b - (np.sum((o - CENTRE) ** 2) - RADIUS**2)
        s = np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
        hits = np.where(np.isfinite(s)[:, None], o + s[:, None] * d, np.nan)
        pts = np.where(np.isfinite(s)[:, None], np.where(np.isfinite(s), s, 0)[:, None] * d_s, np.inf)
        pts = pts.astype(np.float32)  # +inf: how drivers mark "no return"
        return Profile(int(t_ns), "sensor", pts), hits


def _balanced(asm: ProfileAssembler) -> None:
    c = asm.counters
    assert c.balanced, c
    assert c.pending == len(asm._pending)


def _run(asm: ProfileAssembler, profiles) -> list[AssembledScan]:
    out = []
    for p in profiles:
        out += asm.add(p)
        _balanced(asm)
    return out


# -- the synthetic pass -------------------------------------------------------------------------------------------

def test_synthetic_pass_equals_the_points_computed_in_the_fixed_frame():
    rig = Rig()
    buf = rig.buffer()
    stamps = np.arange(0, 1000) * MS + 250_000  # 1 kHz, between the tf samples
    profiles, hits, widths = [], [], []
    for i, s in enumerate(stamps):
        p, h = rig.profile(int(s))
        if i % 7 == 3:  # a driver that drops its trailing points: narrower rows
            p.points, h = p.points[:-13], h[:-13]
        if i % 11 == 5:  # NaN in one coordinate is no return too
            p.points[40, 1] = np.nan
            h[40] = np.nan
        profiles.append(p)
        hits.append(h)
        widths.append(len(h))
    asm = ProfileAssembler(buf, "world", ScanTrigger("count", count=len(stamps)))
    (scan,) = _run(asm, profiles)
    assert scan.end is ScanEnd.COUNT and scan.shape == (1000, 121) and scan.frame_id == "world"
    assert scan.counters.assembled == 1000 and sum(scan.counters.dropped.values()) == 0
    np.testing.assert_array_equal(scan.stamps_ns, stamps)
    np.testing.assert_array_equal(scan.widths, widths)
    want = np.full((1000, 121, 3), np.nan)
    for i, h in enumerate(hits):
        want[i, : len(h)] = h * 1000.0
    # NaN exactly where there was no return or no point; rows keep their width
    np.testing.assert_array_equal(scan.valid, np.all(np.isfinite(want), axis=2))
    assert np.isnan(scan.points[~scan.valid]).all() and 0.1 < scan.valid.mean() < 0.9
    assert not scan.valid[3, 108:].any()
    # within float32 rounding of the sensor-frame metres: the exact hits, on the sphere
    v = scan.valid
    np.testing.assert_allclose(scan.points[v], want[v], atol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(scan.points[v] - CENTRE * 1000, axis=1), RADIUS * 1000, atol=1e-4)
    # and to float64 rounding: the float32 inputs through the analytic pose
    for i in (0, 499, 999):
        t = rig.world_sensor(int(stamps[i]))
        p32 = profiles[i].points.astype(float)
        ok = np.all(np.isfinite(p32), axis=1)
        np.testing.assert_allclose(scan.points[i, : len(p32)][ok], (p32[ok] @ t[:3, :3].T + t[:3, 3]) * 1000,
                                   atol=1e-9)
        np.testing.assert_allclose(scan.sensor_poses[i, :3, :3], t[:3, :3], atol=1e-12)
        np.testing.assert_allclose(scan.sensor_poses[i, :3, 3], t[:3, 3] * 1000, atol=1e-9)
    # the wrist turned 10° across the pass
    r0, r1 = scan.sensor_poses[0, :3, :3], scan.sensor_poses[-1, :3, :3]
    assert np.degrees(Rotation.from_matrix(r0.T @ r1).magnitude()) == pytest.approx(10 * 999 / 1000, abs=1e-9)


def test_per_row_head_poses_follow_the_documented_mapping():
    rig = Rig(duration_ms=50)
    profiles = [rig.profile(s * MS + 500_000, width=41)[0] for s in range(50)]
    (scan,) = _run(ProfileAssembler(rig.buffer(), "world", ScanTrigger("count", count=50)), profiles)
    pos, rot = scan.head_arrays()
    np.testing.assert_allclose(rot, scan.sensor_poses[:, :3, :3] @ np.diag([1.0, -1.0, -1.0]), atol=0)
    np.testing.assert_allclose(pos, scan.sensor_poses[:, :3, 3], atol=0)
    assert np.array_equal(HEAD_IN_SENSOR, np.diag([1.0, -1.0, -1.0]))
    poses = scan.head_poses()
    assert len(poses) == 50 and all(isinstance(p, HeadPose) for p in poses)
    for i in (0, 49):
        # each row's points in its own head frame: on the laser plane (head y = 0), below the head (laser −Z),
        # the line along head +X = sensor x
        head = poses[i].to_head(scan.points[i][scan.valid[i]])
        sensor = profiles[i].points[np.all(np.isfinite(profiles[i].points), axis=1)].astype(float) * 1000
        np.testing.assert_allclose(head[:, 1], 0, atol=1e-6)
        assert np.all(head[:, 2] < -200)
        np.testing.assert_allclose(head[:, 0], sensor[:, 0], atol=1e-6)
        np.testing.assert_allclose(head[:, 2], -sensor[:, 2], atol=1e-6)
        # the laser (head −Z) points down in the world
        assert rot[i, 2, 2] > 0.9


def test_live_stream_with_lagging_tf_assembles_everything_and_holds_few_profiles():
    """tf at 250 Hz arriving 3 ms late, profiles at 1 kHz arriving at once: every profile waits a few ms for its
    tf and is assembled; the held queue never grows."""
    rig = Rig(duration_ms=300)
    buf = TransformBuffer()
    rig.feed_static(buf)
    asm = ProfileAssembler(buf, "world", ScanTrigger("count", count=100))
    events = [(int(s) + 3 * MS, 0, int(s)) for s in rig.tf_stamps()]
    events += [(s * MS + 250_000, 1, s * MS + 250_000) for s in range(300)]
    scans, most = [], 0
    for arrival, kind, stamp in sorted(events):
        if kind == 0:
            rig.feed_dynamic(buf, np.array([stamp]))
            scans += asm.poll(arrival)
        else:
            scans += asm.add(rig.profile(stamp, width=21)[0])
        most = max(most, asm.counters.pending)
        _balanced(asm)
    assert [s.shape[0] for s in scans] == [100, 100, 100] and all(s.end is ScanEnd.COUNT for s in scans)
    assert sum(asm.counters.dropped.values()) == 0 and most <= 8
    ref = _run(ProfileAssembler(rig.buffer(), "world", ScanTrigger("count", count=100)),
               [rig.profile(s * MS + 250_000, width=21)[0] for s in range(300)])
    for a, b in zip(scans, ref, strict=True):
        np.testing.assert_array_equal(a.points, b.points)


@settings(max_examples=40, deadline=None)
@given(rows=st.lists(st.lists(st.sampled_from(["ok", "inf", "nan"]), min_size=1, max_size=8), min_size=1, max_size=6))
def test_rows_keep_their_width_and_invalid_points_stay_nan(rows):
    buf = TransformBuffer()
    q = Rotation.from_euler("xyz", [10, 20, 30], degrees=True)
    buf.set_transform_arrays("w", "s", [0], np.array([[1.0, 2.0, 3.0]]), q.as_quat()[None], static=True)
    rng = np.random.default_rng(len(rows))
    profiles = []
    for i, kinds in enumerate(rows):
        pts = rng.normal(size=(len(kinds), 3)).astype(np.float32)
        for j, k in enumerate(kinds):
            if k == "inf":
                pts[j, 2] = np.inf
            elif k == "nan":
                pts[j] = np.nan
        profiles.append(Profile(i * MS, "s", pts))
    (scan,) = _run(ProfileAssembler(buf, "w", ScanTrigger("count", count=len(rows))), profiles)
    w = max(len(k) for k in rows)
    assert scan.shape == (len(rows), w)
    for i, kinds in enumerate(rows):
        want = np.array([k == "ok" for k in kinds] + [False] * (w - len(kinds)))
        np.testing.assert_array_equal(scan.valid[i], want)
        assert np.isnan(scan.points[i][~want]).all()
        ok = want[: len(kinds)]
        want_pts = (q.apply(profiles[i].points[ok].astype(float)) + np.array([1, 2, 3])) * 1000
        np.testing.assert_allclose(scan.points[i, : len(kinds)][ok], want_pts, atol=1e-9)


# -- triggers -----------------------------------------------------------------------------------------------------

def _stream(rig: Rig, ms: list[int] | range, width: int = 5) -> list[Profile]:
    return [rig.profile(m * MS, width=width)[0] for m in ms]


def test_count_trigger_cuts_every_n_profiles_and_flush_emits_the_rest():
    rig = Rig(duration_ms=200)
    asm = ProfileAssembler(rig.buffer(), "world", ScanTrigger("count", count=30))
    scans = _run(asm, _stream(rig, range(100)))
    scans += asm.flush()
    assert [(s.shape[0], s.end) for s in scans] == [(30, ScanEnd.COUNT)] * 3 + [(10, ScanEnd.FLUSH)]
    assert [int(s.stamps_ns[0] // MS) for s in scans] == [0, 30, 60, 90] and [s.index for s in scans] == [0, 1, 2, 3]
    assert asm.counters.assembled == 100 and asm.counters.scans == 4 and asm.counters.balanced


def test_window_trigger_cuts_at_the_window():
    rig = Rig(duration_ms=200)
    asm = ProfileAssembler(rig.buffer(), "world", ScanTrigger("window", window_s=0.025))
    scans = _run(asm, _stream(rig, range(100)))
    assert [s.shape[0] for s in scans] == [25, 25, 25] and all(s.end is ScanEnd.WINDOW for s in scans)
    assert [int(s.stamps_ns[0] // MS) for s in scans] == [0, 25, 50]
    assert asm.poll(125 * MS)[0].stamps_ns[-1] == 99 * MS  # the clock closes the last window without a profile


def test_gap_trigger_cuts_at_a_pause_in_the_stream():
    rig = Rig(duration_ms=300)
    asm = ProfileAssembler(rig.buffer(), "world", ScanTrigger("gap", gap_s=0.02))
    scans = _run(asm, _stream(rig, [*range(0, 101), *range(200, 301)]))
    assert [(s.shape[0], s.end) for s in scans] == [(101, ScanEnd.GAP)]
    assert asm.poll(330 * MS)[0].shape[0] == 101  # the clock shows the next pause
    assert asm.counters.gaps == 2 and asm.counters.assembled == 202


def test_gap_trigger_cuts_when_the_sensor_stops():
    rig = Rig(duration_ms=800, speed=0.1, stops=[(300, 500)])  # the wrist turns on: ~0.01 m/s while stopped
    asm = ProfileAssembler(rig.buffer(), "world", ScanTrigger("gap", min_speed_m_s=0.03))
    scans = _run(asm, _stream(rig, range(0, 801)))
    scans += asm.flush()
    assert [(s.shape[0], s.end) for s in scans] == [(301, ScanEnd.STOPPED), (300, ScanEnd.FLUSH)]
    assert scans[0].stamps_ns[[0, -1]].tolist() == [0, 300 * MS]
    assert scans[1].stamps_ns[[0, -1]].tolist() == [501 * MS, 800 * MS]
    assert asm.counters.dropped[DropReason.IDLE] == 200 and asm.counters.balanced


def test_a_stationary_start_is_idle_until_the_sensor_moves():
    rig = Rig(duration_ms=200, speed=0.1, stops=[(0, 100)], wrist_deg=1.0)
    asm = ProfileAssembler(rig.buffer(), "world", ScanTrigger("gap", min_speed_m_s=0.03))
    (scan,) = _run(asm, _stream(rig, range(0, 201))) + asm.flush()
    assert scan.stamps_ns[0] == 101 * MS and asm.counters.dropped[DropReason.IDLE] == 101


def test_signal_trigger_takes_the_profiles_between_start_and_stop():
    rig = Rig(duration_ms=100)
    asm = ProfileAssembler(rig.buffer(), "world", ScanTrigger("signal"))
    assert asm.start(10 * MS + 500_000) == [] and asm.stop(40 * MS + 500_000) == []
    scans = _run(asm, _stream(rig, range(60)))
    assert [(s.shape[0], s.end) for s in scans] == [(30, ScanEnd.SIGNAL)]
    assert scans[0].stamps_ns[[0, -1]].tolist() == [11 * MS, 40 * MS]
    assert asm.counters.dropped[DropReason.IDLE] == 30
    # live, with default stamps: between the calls
    live = ProfileAssembler(rig.buffer(), "world", ScanTrigger("signal"))
    profiles = _stream(rig, range(60))
    _run(live, profiles[:5])
    live.start()
    _run(live, profiles[5:25])
    (scan,) = live.stop()
    assert scan.stamps_ns[[0, -1]].tolist() == [5 * MS, 24 * MS] and scan.end is ScanEnd.SIGNAL
    with pytest.raises(ValueError, match="signal trigger"):
        ProfileAssembler(rig.buffer(), "world", ScanTrigger("count", count=3)).start()


def test_stop_waits_for_the_profiles_still_held():
    rig = Rig(duration_ms=100)
    buf = TransformBuffer()
    rig.feed_static(buf)
    rig.feed_dynamic(buf, rig.tf_stamps(until_ms=20))
    asm = ProfileAssembler(buf, "world", ScanTrigger("signal"), tf_timeout_s=1.0)
    asm.start(0)
    _run(asm, _stream(rig, range(40)))
    assert asm.stop() == [] and asm.counters.pending == 19  # 21..39 wait for their tf
    rig.feed_dynamic(buf, rig.tf_stamps()[6:])
    (scan,) = asm.poll()
    assert scan.shape[0] == 40 and scan.end is ScanEnd.SIGNAL


def test_a_pause_cuts_a_count_scan_short():
    rig = Rig(duration_ms=300)
    asm = ProfileAssembler(rig.buffer(), "world", ScanTrigger("count", count=50, gap_s=0.01))
    scans = _run(asm, _stream(rig, [*range(0, 70), *range(100, 160)]))
    assert [(s.shape[0], s.end) for s in scans] == [(50, ScanEnd.COUNT), (20, ScanEnd.GAP), (50, ScanEnd.COUNT)]


def test_min_rows_max_rows_and_bad_profiles():
    rig = Rig(duration_ms=300)
    asm = ProfileAssembler(rig.buffer(), "world", ScanTrigger("gap", gap_s=0.01), min_rows=5, max_rows=40)
    bad = [Profile(1000 * MS, "sensor", np.zeros((4, 2))), Profile(1001 * MS, "sensor", np.zeros((4, 3, 1))),
           Profile(1002 * MS, "sensor", np.zeros((4, 3)), {"i": np.zeros(3)})]
    scans = _run(asm, _stream(rig, [*range(0, 3), *range(50, 100)]) + bad)
    assert [(s.shape[0], s.end) for s in scans] == [(40, ScanEnd.MAX_ROWS)]
    assert asm.counters.dropped[DropReason.SHORT_SCAN] == 3 and asm.counters.dropped[DropReason.BAD_PROFILE] == 3
    assert asm.flush()[0].shape[0] == 10


def test_trigger_settings_are_checked():
    for kw in ({"kind": "count"}, {"kind": "window", "window_s": 0}, {"kind": "gap"}, {"kind": "often"},
               {"kind": "signal", "gap_s": -1}, {"kind": "gap", "min_speed_m_s": 0}):
        with pytest.raises(ValueError):
            ScanTrigger(**kw)  # type: ignore[arg-type]


# -- what is dropped, and why -------------------------------------------------------------------------------------

def test_out_of_order_profiles_are_dropped_and_counted():
    rig = Rig(duration_ms=100)
    asm = ProfileAssembler(rig.buffer(), "world", ScanTrigger("count", count=10))
    (scan,) = _run(asm, _stream(rig, [0, 1, 2, 1, 3, 3, 4, 5, 6, 7, 8, 9]))
    assert scan.stamps_ns.tolist() == [m * MS for m in range(10)]
    assert asm.counters.dropped[DropReason.OUT_OF_ORDER] == 2
    assert asm.recent_drops[-1].reason is DropReason.OUT_OF_ORDER and asm.recent_drops[-1].stamp_ns == 3 * MS


def test_missing_and_unconnected_frames_are_held_then_dropped_with_their_reason():
    rig = Rig(duration_ms=1000)
    buf = rig.buffer()
    buf.set_transform_arrays("cart", "camera", [0], np.zeros((1, 3)), np.array([[0, 0, 0, 1.0]]), static=True)
    asm = ProfileAssembler(buf, "world", ScanTrigger("count", count=5), tf_timeout_s=0.05)
    ghost = [Profile(m * MS, "ghost", np.zeros((3, 3), np.float32)) for m in range(0, 10)]
    _run(asm, ghost)
    assert asm.counters.pending == 10 and asm.counters.dropped[DropReason.TF_MISSING] == 0  # held, may yet come
    camera = [Profile(m * MS, "camera", np.zeros((3, 3), np.float32)) for m in range(10, 20)]
    _run(asm, camera)
    scans = _run(asm, _stream(rig, range(100, 105)))
    assert asm.counters.dropped[DropReason.TF_MISSING] == 10
    assert asm.counters.dropped[DropReason.TF_NOT_CONNECTED] == 10
    assert [s.shape[0] for s in scans] == [5] and asm.counters.pending == 0
    assert "ghost" in next(d.detail for d in asm.recent_drops if d.reason is DropReason.TF_MISSING)


def test_late_tf_is_waited_for_then_dropped_after_the_timeout():
    rig = Rig(duration_ms=1000)
    buf = TransformBuffer()
    rig.feed_static(buf)
    rig.feed_dynamic(buf, rig.tf_stamps(until_ms=100))
    asm = ProfileAssembler(buf, "world", ScanTrigger("count", count=1000), tf_timeout_s=0.1)
    _run(asm, _stream(rig, range(0, 150)))
    assert asm.counters.pending == 49  # 101..149 wait
    rig.feed_dynamic(buf, rig.tf_stamps(until_ms=200)[26:])  # the tf arrives in time: nothing lost
    asm.poll()
    assert asm.counters.pending == 0 and sum(asm.counters.dropped.values()) == 0
    _run(asm, _stream(rig, range(150, 330)))  # the tf stops at 200 ms: 201..229 time out at 330 ms
    assert asm.counters.dropped[DropReason.TF_LATE] == 29 and asm.counters.pending == 100
    asm.flush()
    assert asm.counters.dropped[DropReason.TF_LATE] == 129 and asm.counters.in_progress == 0
    assert asm.counters.assembled == 201 and asm.counters.balanced


def test_profiles_older_than_the_tf_history_are_dropped_at_once():
    rig = Rig(duration_ms=3000)
    buf = TransformBuffer(cache_time_ns=1000 * MS)
    rig.feed_static(buf)
    rig.feed_dynamic(buf, rig.tf_stamps(until_ms=3000))
    asm = ProfileAssembler(buf, "world", ScanTrigger("count", count=3), tf_timeout_s=10.0)
    scans = _run(asm, _stream(rig, [500, 1500, 2500, 2600, 2700]))
    assert asm.counters.dropped[DropReason.TF_PAST] == 2 and asm.counters.pending == 0
    assert [s.stamps_ns.tolist() for s in scans] == [[2500 * MS, 2600 * MS, 2700 * MS]]


def test_the_held_queue_is_bounded():
    rig = Rig(duration_ms=100)
    buf = TransformBuffer()
    rig.feed_static(buf)  # no robot tf at all: nothing resolves
    asm = ProfileAssembler(buf, "world", ScanTrigger("count", count=5), tf_timeout_s=1e6, max_pending=50)
    for m in range(500):
        asm.add(rig.profile(m * MS, width=3)[0] if m < 100 else Profile(m * MS, "sensor", np.zeros((3, 3))))
        assert asm.counters.pending <= 50
        _balanced(asm)
    assert asm.counters.dropped[DropReason.QUEUE_FULL] == 450 and asm.counters.pending == 50


def test_sensor_frame_setting_overrides_the_profile_frame_id():
    rig = Rig(duration_ms=600)
    asm = ProfileAssembler(rig.buffer(), "world", ScanTrigger("count", count=5), sensor_frame="sensor")
    profiles = _stream(rig, range(400, 405))
    for p in profiles:
        p.frame_id = "laser_link_the_driver_names"
    (scan,) = _run(asm, profiles)
    assert scan.sensor_frame == "sensor" and scan.valid.any()


def test_extra_fields_are_stacked_and_padded():
    buf = TransformBuffer()
    buf.set_transform_arrays("w", "s", [0], np.zeros((1, 3)), np.array([[0, 0, 0, 1.0]]), static=True)
    pts = lambda n: np.ones((n, 3), np.float32)  # noqa: E731
    profiles = [Profile(0, "s", pts(3), {"intensity": np.array([1, 2, 3], np.float32),
                                          "line": np.array([7, 7, 7], np.uint16)}),
                Profile(1, "s", pts(2), {"intensity": np.array([4, 5], np.float32),
                                          "line": np.array([8, 8], np.uint16), "width": np.array([1, 2])}),]
    (scan,) = _run(ProfileAssembler(buf, "w", ScanTrigger("count", count=2)), profiles)
    i, line, width = scan.fields["intensity"], scan.fields["line"], scan.fields["width"]
    assert i.dtype == np.float32 and np.array_equal(i, np.array([[1, 2, 3], [4, 5, np.nan]]), equal_nan=True)
    assert line.dtype == np.uint16 and line.tolist() == [[7, 7, 7], [8, 8, 0]]
    assert width.dtype == np.float64 and np.array_equal(width, [[np.nan] * 3, [1, 2, np.nan]], equal_nan=True)
