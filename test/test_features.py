"""Features: each of the study's features by hand on constructed points, the registry, field_<name>."""

from __future__ import annotations

import numpy as np
import pytest

from xmetro_ros.judge import features as F
from xmetro_ros.preprocess import Prepared, prepare_scan
from xmetro_ros.scan.artifacts import Sphere
from xmetro_ros.scan.geometry import HeadPose, point_geometry
from xmetro_ros.scan.scan import Scan
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings

S = ScanSettings(6.0, 3.0, 0.1)


def ctx_for(points: np.ndarray, normals: np.ndarray, pose: HeadPose | None = None, fields=None) -> F.FeatureContext:
    pose = pose or HeadPose.looking_down(90.0)
    g = point_geometry(np.asarray(points, float), pose, 52.0, dtype=np.float32)
    n = np.asarray(normals, np.float32)
    return F.FeatureContext(normals=n, L=g.L, V=g.V, standoff=g.standoff, source_distance=g.source_distance,
                            settings=S, fields=fields or {}, points=np.asarray(points, float), u=g.u, s=g.s,
                            camera_mm=(0.0, 52.0, 0.0))


def row(ctx: F.FeatureContext, i: int = 0) -> dict[str, float]:
    x = F.compute_features(F.STUDY_FEATURES, ctx)
    return dict(zip(F.STUDY_FEATURES, x[i].tolist(), strict=True))


def test_study_feature_list():
    assert F.STUDY_FEATURES == ["lateral_density", "direction_density", "exposure_time", "N_x", "N_y", "N_z",
                                "ori_x", "ori_y", "ori_z", "oriCMOS_y", "Inc", "ViewAng", "R_y", "ang"]
    units = {f["name"]: f["unit"] for f in F.REGISTRY.describe(F.STUDY_FEATURES)}
    assert units["exposure_time"] == "ms" and units["R_y"] == "mm" and units["ang"] == "deg"


def test_normal_facing_the_laser():
    # Point right below the source (0, 0, 10): L = (0, 0, 1); normal N = L (so N = -(-L)): Inc = 1, ang = 0.
    c = ctx_for([[0.0, 0.0, 10.0]], [[0.0, 0.0, 1.0]])
    r = row(c)
    assert (r["lateral_density"], r["direction_density"], r["exposure_time"]) == (6.0, 3.0, pytest.approx(0.1))
    assert (r["N_x"], r["N_y"], r["N_z"]) == (0.0, 0.0, 1.0)
    assert r["ori_x"] == 0 and r["ori_y"] == 0 and r["ori_z"] == pytest.approx(0.0, abs=1e-7)
    assert r["Inc"] == pytest.approx(1.0)
    assert r["ang"] == pytest.approx(0.0, abs=1e-3)
    assert r["R_y"] == pytest.approx(80.0)  # 90 - Z
    # camera 52 mm along +Y at the source height: V = (0, 52, 80)/|.|
    v = np.array([0.0, 52.0, 80.0]) / np.hypot(52.0, 80.0)
    assert r["ViewAng"] == pytest.approx(v[2], rel=1e-6)
    assert r["oriCMOS_y"] == pytest.approx(-v[1], rel=1e-6)


def test_normal_opposite_the_laser():
    # N = -L: Inc = -1, ang = 180, ori = N - L = 2N.
    c = ctx_for([[0.0, 0.0, 10.0]], [[0.0, 0.0, -1.0]])
    r = row(c)
    assert r["Inc"] == pytest.approx(-1.0)
    assert r["ang"] == pytest.approx(180.0, abs=1e-3)
    assert (r["ori_x"], r["ori_y"], r["ori_z"]) == pytest.approx((0.0, 0.0, -2.0))


def test_oblique_point_by_hand():
    # Point at (30, 5, 50): the source that lit it is (0, 5, 90); L = (-30, 0, 40)/50 = (-0.6, 0, 0.8).
    n = np.array([1.0, 0.0, 1.0]) / np.sqrt(2)
    r = row(ctx_for([[30.0, 5.0, 50.0]], [n]))
    lv = np.array([-0.6, 0.0, 0.8])
    vv = np.array([-30.0, 52.0, 40.0]) / np.linalg.norm([-30.0, 52.0, 40.0])
    assert r["Inc"] == pytest.approx(n @ lv, abs=1e-6)
    assert r["ViewAng"] == pytest.approx(n @ vv, abs=1e-6)
    assert (r["ori_x"], r["ori_y"], r["ori_z"]) == pytest.approx(tuple(n - lv), abs=1e-6)
    assert r["oriCMOS_y"] == pytest.approx(n[1] - vv[1], abs=1e-6)
    assert r["R_y"] == pytest.approx(40.0)
    assert r["ang"] == pytest.approx(np.degrees(np.arctan2(np.linalg.norm(np.cross(n, lv)), n @ lv)), abs=1e-3)


def test_many_points_match_reference_and_dtype():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-20, 20, (1000, 3))
    n = rng.normal(size=(1000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    c = ctx_for(pts, n)
    x = F.compute_features(F.STUDY_FEATURES, c)
    assert x.shape == (1000, 14) and x.dtype == np.float32
    lv = c.L.astype(float)
    ang = np.degrees(np.arctan2(np.linalg.norm(np.cross(n, lv), axis=1), np.einsum("ij,ij->i", n, lv)))
    assert np.allclose(x[:, 13], ang, atol=0.05)
    assert np.allclose(x[:, 12], 90 - pts[:, 2], atol=1e-4)
    x64 = F.compute_features(["Inc"], c, dtype=np.float64)
    assert x64.dtype == np.float64


def test_registry_errors_and_registration():
    with pytest.raises(F.UnknownFeatureError, match="'nope'"):
        F.REGISTRY.get("nope")
    c = ctx_for([[0.0, 0.0, 10.0]], [[0.0, 0.0, 1.0]], fields={"intensity": np.array([0.25], np.float32)})
    with pytest.raises(F.UnknownFeatureError):
        F.compute_features(["Inc", "bogus"], c)
    with pytest.raises(F.MissingFieldError, match="'t'") as e:
        F.compute_features(["Inc", "field_t"], c)
    assert isinstance(e.value, ValueError) and e.value.field_name == "t"
    assert F.compute_features(["field_intensity", "Inc"], c)[0].tolist() == [0.25, 1.0]
    assert F.required_fields(["Inc", "field_intensity", "field_u"]) == {"intensity", "u"}
    reg = F.FeatureRegistry()
    f = reg.register("gain", "1", "intensity × 2", ["field:intensity"], lambda ctx: ctx.field("intensity") * 2)
    assert reg.names() == ["gain"] and f.fields == ("intensity",)
    assert F.compute_features(["gain"], c, registry=reg)[0, 0] == 0.5
    with pytest.raises(F.FeatureError, match="already registered"):
        reg.register("gain", "1", "", [], lambda ctx: 0.0)
    reg.register("gain", "1", "", [], lambda ctx: 3.0, replace_existing=True)
    assert F.compute_features(["gain"], c, registry=reg)[0, 0] == 3.0
    reg.register("bad_shape", "1", "", [], lambda ctx: np.zeros(5))
    with pytest.raises(F.FeatureError, match="bad_shape"):
        F.compute_features(["bad_shape"], c, registry=reg)
    with pytest.raises(F.FeatureError, match="list of feature names"):
        F.compute_features("Inc", c)


def test_degenerate_normals_rejected():
    c = ctx_for([[0.0, 0.0, 10.0], [1.0, 0.0, 10.0]], [[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    with pytest.raises(F.FeatureError, match=r"degenerate.*point 1"):
        F.compute_features(["Inc"], c)
    c = ctx_for([[0.0, 0.0, 10.0]], [[np.nan, 0.0, 1.0]])
    with pytest.raises(F.FeatureError, match="degenerate"):
        F.compute_features(F.STUDY_FEATURES, c)
    assert F.compute_features(["lateral_density", "R_y"], c).shape == (1, 2)  # features without N still work


def test_context_shape_checks():
    with pytest.raises(F.FeatureError, match="L must have shape"):
        F.FeatureContext(np.zeros((3, 3)), np.zeros((2, 3)), np.zeros((3, 3)), np.zeros(3), np.zeros(3), S)
    with pytest.raises(F.FeatureError, match="field 'i'"):
        F.FeatureContext(np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros(3), np.zeros(3), S,
                         fields={"i": np.zeros(4)})


def test_from_prepared_with_pose_and_settings():
    scanner = ScannerModel.load()
    ys = np.linspace(-10, 10, 40)
    a = np.radians(np.linspace(-15, 15, 50))
    d = np.stack([np.sin(a), 0 * a, -np.cos(a)], 1)
    o = np.zeros((40, 50, 3))
    o[..., 1] = ys[:, None]
    o[..., 2] = 90
    dd = np.broadcast_to(d, (40, 50, 3)).reshape(-1, 3)
    t = Sphere(20.0).intersect(o.reshape(-1, 3), dd)
    pts = (o.reshape(-1, 3) + dd * t[:, None]).reshape(40, 50, 3)
    scan = Scan(pts, S, HeadPose.looking_down(90.0, y_mm=-10), "xm-ls90", fields={"intensity": np.ones((40, 50))})
    prep: Prepared = prepare_scan(scan, scanner=scanner)
    c = F.FeatureContext.from_prepared(prep)
    x = F.compute_features([*F.STUDY_FEATURES, "field_intensity"], c)
    assert x.shape == (len(prep), 15) and np.isfinite(x).all()
    # seen from 10 mm higher: R_y grows by 10, normals unchanged
    c2 = c.with_pose(HeadPose.looking_down(100.0, y_mm=-10))
    x2 = F.compute_features(["R_y", "N_z"], c2)
    assert np.allclose(x2[:, 0], x[:, 12] + 10, atol=1e-3) and np.array_equal(x2[:, 1], x[:, 5])
    c3 = c.with_settings(ScanSettings(15.0, 5.0, 2.0))
    assert F.compute_features(["lateral_density", "exposure_time"], c3)[0].tolist() == [15.0, 2.0]
    assert F.compute_features(["lateral_density"], c)[0, 0] == 6.0  # original untouched
    sub = c.subset(np.arange(0, len(prep), 3))
    assert np.array_equal(F.compute_features(F.STUDY_FEATURES, sub), x[::3, :14])
