"""Learning tables and the study's protocol splits."""

from __future__ import annotations

import numpy as np
import pytest

from xmetro_ros.calibrate import dataset as D
from xmetro_ros.judge.features import STUDY_FEATURES
from xmetro_ros.scan.artifacts import Cylinder, Sphere
from xmetro_ros.scan.geometry import HeadPose
from xmetro_ros.scan.scan import Scan
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings


def grid_scan(art, settings: ScanSettings, h: int = 50, w: int = 60, shift: float = 0.0) -> Scan:
    ys = np.linspace(-10, 10, h)
    a = np.radians(np.linspace(-15, 15, w))
    d = np.stack([np.sin(a), 0 * a, -np.cos(a)], 1)
    o = np.zeros((h, w, 3))
    o[..., 1] = ys[:, None]
    o[..., 2] = 90
    dd = np.broadcast_to(d, (h, w, 3)).reshape(-1, 3)
    t = art.intersect(o.reshape(-1, 3), dd)
    p = o.reshape(-1, 3) + dd * (t - shift)[:, None]  # shift > 0: measured outside the surface, along the ray
    return Scan(p.reshape(h, w, 3), settings, HeadPose.looking_down(90.0, y_mm=-10), "xm-ls90", artifact=art,
                fields={"intensity": np.full((h, w), 0.5, np.float32)})


@pytest.fixture(scope="module")
def scanner():
    return ScannerModel.load()


def test_study_split_protocol():
    sizes = [400, 1000, 150]
    sp = D.study_split(sizes, seed=7)
    offsets = np.cumsum([0, *sizes])
    assert len(sp.train) == 300 and len(sp.tests) == 5 and all(len(t) == 150 for t in sp.tests)
    for k in range(3):
        tr = sp.train[(sp.train >= offsets[k]) & (sp.train < offsets[k + 1])]
        assert len(tr) == 100 and len(set(tr)) == 100
        for t in sp.tests:
            te = t[(t >= offsets[k]) & (t < offsets[k + 1])]
            assert len(te) == 50 and len(set(te)) == 50 and not set(te) & set(tr)
    again = D.study_split(sizes, seed=7)
    assert np.array_equal(again.train, sp.train) and not np.array_equal(D.study_split(sizes, seed=8).train, sp.train)
    with pytest.raises(D.DatasetError, match="at least 150"):
        D.study_split([149])
    with pytest.raises(D.DatasetError, match="no clouds"):
        D.study_split([])


def test_build_table_constructed_scans(scanner):
    scans = [grid_scan(Sphere(20.0), ScanSettings(6, 3, 0.1)), grid_scan(Sphere(20.0), ScanSettings(10, 4, 0.5),
                                                                            shift=0.05),
             grid_scan(Cylinder(15.0), ScanSettings(15, 5, 2.0))]
    names = [*STUDY_FEATURES, "field_intensity"]
    tab = D.build_table(scans, names, max_points_per_cloud=500, seed=1, scanner=scanner)
    assert tab.X.dtype == np.float32 and tab.X.shape[1] == 15 and tab.feature_names == names
    assert np.bincount(tab.cloud_id).tolist() == [500, 500, 500]
    assert np.isnan(tab.oracle).all()  # no expected_error on constructed scans
    assert np.abs(tab.y[tab.cloud_id == 0]).max() < 1e-9  # exact sphere
    # measured 0.05 mm outside along the ray: radial error ≈ -0.05 × cos(incidence) < 0 on the +Z side
    y1 = tab.y[tab.cloud_id == 1]
    assert np.all(y1[:, 2] < 0) and np.all(np.linalg.norm(y1, axis=1) < 0.051)
    assert np.all(tab.y[tab.cloud_id == 2][:, 1] == 0)  # cylinder: axial projection
    assert tab.clouds[2]["artifact"]["kind"] == "cylinder" and tab.clouds[1]["label"] == "lat10_dir4_exp0.5"
    # features of the settings are the clouds' settings
    assert np.all(tab.X[tab.cloud_id == 2, 0] == 15)
    sp = D.study_split(tab, seed=0)
    assert set(np.unique(tab.cloud_id[sp.train])) == {0, 1, 2}
    tr, te = D.cloud_split(tab, test_fraction=0.34, seed=0)
    assert len(tr) + len(te) == len(tab) and not set(tab.cloud_id[tr]) & set(tab.cloud_id[te])
    sub = tab.rows(te)
    assert len(sub) == len(te)


def test_build_table_simulated_oracle(scanner):
    from xmetro_ros.sim import simulate_scan

    art = Sphere(17.5)
    scan = simulate_scan(art, ScanSettings(6, 3, 0.1), scanner=scanner, seed=2)
    tab = D.build_table([scan], STUDY_FEATURES, max_points_per_cloud=None, scanner=scanner)
    assert len(tab) > 0.95 * scan.n_valid
    assert np.isfinite(tab.oracle).all() and np.isfinite(tab.X).all()
    # oracle and targets belong to the same points of the scan
    ee = scan.expected_error.reshape(-1, 3)[tab.point_index]
    assert np.array_equal(ee, tab.oracle)
    assert np.allclose(tab.y, art.errors(scan.points.reshape(-1, 3)[tab.point_index]))


def test_bad_inputs(scanner):
    s = grid_scan(Sphere(20.0), ScanSettings(6, 3, 0.1))
    no_art = Scan(s.points, s.settings, s.pose, s.scanner_id)
    with pytest.raises(D.DatasetError, match="no artifact"):
        D.build_table([no_art], STUDY_FEATURES, scanner=scanner)
    with pytest.raises(D.DatasetError, match="no scans"):
        D.build_table([], STUDY_FEATURES, scanner=scanner)
    with pytest.raises(D.DatasetError, match="no feature"):
        D.build_table([s], [], scanner=scanner)
    from xmetro_ros.judge.features import UnknownFeatureError

    with pytest.raises(UnknownFeatureError):
        D.build_table([s], ["N_x", "nope"], scanner=scanner)
    tab = D.build_table([s], STUDY_FEATURES, max_points_per_cloud=200, scanner=scanner)
    with pytest.raises(D.DatasetError, match="two groups"):
        D.cloud_split(tab)
    with pytest.raises(D.DatasetError, match="test_fraction"):
        D.cloud_split(tab, test_fraction=1.5)
