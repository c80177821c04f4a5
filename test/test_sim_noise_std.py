"""The simulator's per-point truth of the random part (Scan.noise_std): repeated simulations of the same scan with
different seeds scatter each point's error per axis with exactly that std; injected outliers are flagged and left
out; build_table carries it as the oracle_std column."""

from __future__ import annotations

import numpy as np
import pytest

from xmetro_ros.calibrate.dataset import build_table
from xmetro_ros.scan.artifacts import Cylinder, Plane, Sphere
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim import simulate_scan
from xmetro_ros.sim.speckle import correlated_field, correlated_field_std

SC = ScannerModel.load()
N_SEEDS = 120


def _repeat(artifact, settings, n=N_SEEDS):
    scans = [simulate_scan(artifact, settings, scanner=SC, seed=s) for s in range(n)]
    v = scans[0].valid_mask()
    for s in scans[1:]:  # which points return is deterministic (no effect drops points at random)
        assert np.array_equal(s.valid_mask(), v)
    err = np.stack([artifact.errors(s.points.reshape(-1, 3)[v]) for s in scans])  # (n, M, 3)
    out = np.stack([s.injected_outlier.reshape(-1)[v] for s in scans])  # (n, M)
    assert [int(o.sum()) for o in out] == [s.meta["n_outliers"] for s in scans]
    std = np.stack([s.noise_std.reshape(-1, 3)[v] for s in scans])
    exp = np.stack([s.expected_error.reshape(-1, 3)[v] for s in scans])
    assert np.allclose(std, std[0]) and np.allclose(exp, exp[0])  # truth does not depend on the seed
    return err, out, std[0], exp[0]


@pytest.mark.parametrize(("artifact", "settings"), [
    (Sphere(12.0), ScanSettings(2.0, 1.0, 0.1)),  # short exposure: x2.2 noise
    (Sphere(12.0), ScanSettings(4.0, 2.0, 2.0)),  # saturation widening, more blur averaging speckle
    (Cylinder(8.0, axis=(1.0, 0.0, 0.0)), ScanSettings(2.0, 1.5, 0.5)),
    (Plane((0.0, 0.0, 0.0), (0.5, 0.0, 1.0)), ScanSettings(2.0, 1.0, 0.5)),  # tilted plane: error along its normal
])
def test_empirical_std_over_seeds_matches_noise_std(artifact, settings):
    err, out, std, exp = _repeat(artifact, settings)
    assert out.any()  # the outliers effect is on and its returns are flagged ...
    dev = np.abs(err - exp)
    # ... and they are far off (0.2-1.5 mm along the ray; less of it reaches the error at grazing incidence)
    assert np.median(np.linalg.norm(dev[out], axis=-1)) > 0.2
    clean = ~out.any(axis=0)  # points never an outlier in any seed
    e, s = err[:, clean], std[clean]
    # The mean over seeds is the expected error (the random part has zero mean).
    se = s / np.sqrt(N_SEEDS)
    assert np.mean(np.abs(e.mean(0) - exp[clean]) <= 3.5 * se + 1e-9) > 0.99
    emp = e.std(axis=0, ddof=1)
    big = s > 1e-4  # axes the normal does not reach carry (almost) no random error
    rel = 1.0 / np.sqrt(2 * (N_SEEDS - 1))  # sampling error of a std estimate
    assert (big.sum(0) > 200).sum() >= 2  # a cylinder along X has no X error at all
    for a in range(3):
        m = big[:, a]
        if not m.any():
            assert np.all(emp[:, a] < 5e-4)
            continue
        ratio = emp[m, a] / s[m, a]
        assert abs(np.mean(ratio**2) - 1) < 0.04, (a, np.mean(ratio**2))  # pooled variance ratio
        assert np.percentile(np.abs(ratio - 1), 95) < 2.5 * rel, a  # and point by point
        # Where the truth is ~0 the scatter is ~0 too.
        assert np.all(emp[~m, a] < 5e-4)
    # On curved artifacts the std varies across the cloud (grazing incidence, view): not one constant.
    if not isinstance(artifact, Plane):
        assert np.percentile(s[:, 2], 95) > 1.5 * np.percentile(s[:, 2], 5)


def test_short_exposure_widens_noise_std():
    a = simulate_scan(Sphere(12.0), ScanSettings(2.0, 1.0, 0.1), scanner=SC, seed=0)
    b = simulate_scan(Sphere(12.0), ScanSettings(2.0, 1.0, 0.5), scanner=SC, seed=0)
    both = a.valid_mask() & b.valid_mask()
    za, zb = a.noise_std.reshape(-1, 3)[both, 2], b.noise_std.reshape(-1, 3)[both, 2]
    assert np.median(za / zb) > 1.6  # sqrt(5) on the incidence noise, speckle less averaged by blur


def test_correlated_field_std_is_exact_on_small_grids():
    rng = np.random.default_rng(0)
    for shape, sig, n in [((6, 5), (3.0, 2.5), 4000), ((200, 150), (1.2, 0.6), 100), ((4, 300), (2.0, 0.0), 400)]:
        f = np.stack([correlated_field(shape, sig, rng) for _ in range(n)])
        rms = np.sqrt(np.mean(f**2))  # zero-mean field
        want = correlated_field_std(shape, sig)
        assert abs(rms / want - 1) < 0.04, (shape, rms, want)
    assert correlated_field_std((6, 5), (3.0, 2.5)) > 1.5  # the wrap-around really matters there
    assert abs(correlated_field_std((200, 150), (1.2, 0.6)) - 1) < 1e-3  # and not on real grids


def test_build_table_carries_oracle_std():
    scans = [simulate_scan(Sphere(12.0), ScanSettings(2.0, 1.0, 0.5), scanner=SC, seed=s) for s in (1, 2)]
    tab = build_table(scans, ["Inc", "N_z"], max_points_per_cloud=500)
    assert tab.oracle_std.shape == tab.y.shape
    for k, s in enumerate(scans):
        rows = tab.cloud_id == k
        want = s.noise_std.reshape(-1, 3)[tab.point_index[rows]]
        inj = s.injected_outlier.reshape(-1)[tab.point_index[rows]]
        got = tab.oracle_std[rows]
        np.testing.assert_allclose(got[~inj], want[~inj])
        assert np.isnan(got[inj]).all()
    sub = tab.rows(np.arange(10))
    np.testing.assert_array_equal(sub.oracle_std, tab.oracle_std[:10])
