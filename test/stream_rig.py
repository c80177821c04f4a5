"""A virtual scanner's pass replayed as a line-scanner driver streams it: one profile per row in the sensor frame
(float32 metres, +inf for no return), stamped at the profile period, posed by tf (a robot flange moving the sensor
through the hand-eye transform). The ground truth of the profile-stream tests: the profiles, assembled in the
artifact frame from that tf, must give back the simulator's own organized scan.

Frames: ``artifact`` (the scan frame: fixed frame of the assembly) ← ``flange`` (dynamic, sampled every ``tf_ms``;
the motion is linear in time, so interpolating the samples is exact) ← ``sensor`` (static hand-eye). The sensor's
axes follow line-scanner drivers (x along the line, z the range): R(artifact ← sensor) = R_head · HEAD_IN_SENSOR.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from xmetro_ros.scan.assembly import HEAD_IN_SENSOR
from xmetro_ros.scan.scan import Scan
from xmetro_ros.scan.scanner import ScannerModel
from xmetro_ros.scan.tf_buffer import TransformBuffer

MS = 1_000_000  # ns
T0_NS = 1_700_000_000 * 1_000_000_000  # a wall-clock-like start, as a driver stamps

# flange ← sensor: a hand-eye transform that is not the identity (metres)
HAND_EYE_R = Rotation.from_euler("xyz", [2.0, -1.0, 3.0], degrees=True).as_matrix()
HAND_EYE_T = np.array([0.012, -0.004, 0.085])


def transform(r: np.ndarray, p: np.ndarray) -> np.ndarray:
    """4×4 homogeneous transform from a rotation (3, 3) and a translation (3,)."""
    out = np.eye(4)
    out[:3, :3] = r
    out[:3, 3] = p
    return out


@dataclass
class SimPass:
    """The stream of one simulated organized scan.

    Attributes:
        scan: the simulator's scan (points mm, artifact frame).
        profiles: (H, W, 3) float32 sensor-frame metres, +inf where the row has no return.
        stamps_ns: (H,) each profile's stamp.
        sensor_poses: (H, 4, 4) T(artifact ← sensor), metres.
        period_s: the profile period.
    """

    scan: Scan
    profiles: np.ndarray
    stamps_ns: np.ndarray
    sensor_poses: np.ndarray
    period_s: float

    @property
    def speed_m_s(self) -> float:
        return float(np.linalg.norm(self.sensor_poses[1, :3, 3] - self.sensor_poses[0, :3, 3]) / self.period_s)

    def flange(self, t_ns: np.ndarray) -> np.ndarray:
        """T(artifact ← flange) at ``t_ns`` (linear in time through the rows' poses; extrapolated at both ends)."""
        t = (np.asarray(t_ns, dtype=np.int64) - self.stamps_ns[0]) / 1e9
        p0 = self.sensor_poses[0, :3, 3]
        v = (self.sensor_poses[1, :3, 3] - p0) / self.period_s
        he_inv = np.linalg.inv(transform(HAND_EYE_R, HAND_EYE_T))
        out = np.empty((len(t), 4, 4))
        for i, ti in enumerate(t):
            out[i] = transform(self.sensor_poses[0, :3, :3], p0 + v * ti) @ he_inv
        return out

    def tf_stamps(self, tf_ms: float = 4.0) -> np.ndarray:
        """tf sample stamps covering the pass with one sample to spare on each side (250 Hz by default)."""
        step = round(tf_ms * MS)
        return np.arange(int(self.stamps_ns[0]) - step, int(self.stamps_ns[-1]) + 2 * step, step, dtype=np.int64)

    def feed(self, buf: TransformBuffer, tf_ms: float = 4.0) -> None:
        """Static hand-eye + the flange samples into ``buf``."""
        buf.set_transform_arrays("flange", "sensor", [0], HAND_EYE_T[None],
                                 Rotation.from_matrix(HAND_EYE_R).as_quat()[None], static=True)
        st = self.tf_stamps(tf_ms)
        m = self.flange(st)
        buf.set_transform_arrays("artifact", "flange", st, m[:, :3, 3], Rotation.from_matrix(m[:, :3, :3]).as_quat())

    def buffer(self, tf_ms: float = 4.0) -> TransformBuffer:
        buf = TransformBuffer()
        self.feed(buf, tf_ms)
        return buf


def sim_pass(scan: Scan, scanner: ScannerModel, t0_ns: int = T0_NS) -> SimPass:
    """The stream of ``scan`` (a simulator scan from its default grid: row i taken ``i / direction_density`` mm along
    the start pose's +Y, one profile period after row i − 1)."""
    pts = np.asarray(scan.points, dtype=np.float64)
    h, _w = pts.shape[:2]
    s = np.arange(h) / scan.settings.direction_density
    r_head = scan.pose.rotation
    origins = scan.pose.position + s[:, None] * r_head[:, 1]  # mm
    r_sensor = r_head @ HEAD_IN_SENSOR
    local = np.einsum("hwi,ij->hwj", pts - origins[:, None, :], r_sensor) / 1000.0  # p_s = R^T (p - o), m
    profiles = np.where(np.isfinite(local).all(axis=2, keepdims=True), local, np.inf).astype(np.float32)
    period = max(1.0 / scanner.profile_rate_hz, scan.settings.exposure_ms * 1e-3)
    stamps = t0_ns + np.round(np.arange(h) * period * 1e9).astype(np.int64)
    poses = np.tile(np.eye(4), (h, 1, 1))
    poses[:, :3, :3] = r_sensor
    poses[:, :3, 3] = origins / 1000.0
    return SimPass(scan, profiles, stamps, poses, period)
