"""Calibration of the simulator's noise against real AT C5 laser-line profiles of a 40 mm radius sphere."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import need_shared

from xmetro_ros.sim.calibration import (
    ANGLE_BINS,
    calibration_table,
    clean_and_fit,
    fit_circle,
    load_atc5_profiles,
)

ATC5 = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "measured" / "atc5_profiler_sphere_r40"


def test_circle_fit_recovers_a_noisy_arc():
    rng = np.random.default_rng(0)
    a = np.linspace(np.radians(20), np.radians(160), 800)
    xz = np.c_[5 + 30 * np.cos(a), -7 + 30 * np.sin(a)] + rng.normal(0, 0.01, (800, 2))
    c, r, res = fit_circle(xz)
    assert np.allclose(c, [5, -7], atol=0.01) and r == pytest.approx(30, abs=0.01)
    assert res.std() == pytest.approx(0.01, rel=0.15)
    # Gross errors are removed before the final fit; angles are measured from +z (the sensor axis).
    xz[::100, 1] += 1.0
    f = clean_and_fit(xz)
    assert f.n_used == 792 and f.angle_deg.min() < 1 and 69 < f.angle_deg.max() < 71


def test_loader_reads_the_15_profiles():
    need_shared(ATC5)
    profiles = load_atc5_profiles(ATC5)
    assert len(profiles) == 15
    assert all(p.ndim == 2 and p.shape[1] == 2 and 1300 <= len(p) <= 2600 for p in profiles)
    with pytest.raises(FileNotFoundError):
        load_atc5_profiles(ATC5 / "nothing_here")


def test_simulated_noise_matches_measured_profiles():
    """Binned circle-fit residual RMS of simulated vs real profiles, within the stated relative tolerance
    (20 % below 60 deg, 25 % at 60-80 deg). The >80 deg bin (15 measured points) is reported, not tested."""
    need_shared(ATC5)
    rows = calibration_table(ATC5, seed=0)
    assert [r["bin_deg"] for r in rows] == list(ANGLE_BINS)
    meas = [r["measured_um"] for r in rows[:3]]
    # The real figures the brief quotes: ~8-11, 14-17, 21-26 um.
    assert 8 < meas[0] < 11 and 14 < meas[1] < 18 and 21 < meas[2] < 27
    for r in rows[:3]:
        assert r["measured_n"] >= 100 and r["simulated_n"] >= 100
        assert abs(r["ratio"] - 1) <= r["tolerance"], r
    assert rows[0]["simulated_um"] < rows[1]["simulated_um"] < rows[2]["simulated_um"]
