"""Targets (eq. 8-15) and fits: exact shapes give zero error, known offsets known errors, fitted centres."""

from __future__ import annotations

import numpy as np
import pytest

from xmetro_ros.scan import fitting, targets
from xmetro_ros.scan.artifacts import Cylinder, Plane, Sphere


def sphere_points(r: float, c=(0.0, 0.0, 0.0), n: int = 500, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2])  # upper half, as a scanner from above sees it
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(c) + r * d


def test_exact_shapes_have_zero_error():
    assert np.abs(targets.point_errors(sphere_points(20.0), Sphere(20.0))).max() < 1e-12
    rng = np.random.default_rng(1)
    th = rng.uniform(0, np.pi, 300)
    p = np.stack([15 * np.cos(th), rng.uniform(-30, 30, 300), 15 * np.sin(th)], 1)
    assert np.abs(targets.point_errors(p, Cylinder(15.0))).max() < 1e-12


def test_known_radial_offsets_sphere():
    p0 = sphere_points(20.0)
    n = p0 / 20.0
    delta = np.linspace(-0.1, 0.1, len(p0))[:, None]
    e = targets.point_errors(p0 + delta * n, Sphere(20.0))
    assert np.allclose(e, -delta * n, atol=1e-12)  # nominal - measured: outside → negative along +n
    # eq. 13-15 by hand on one point: (0, 0, 20.05) → error (0, 0, -0.05)
    assert np.allclose(targets.point_errors(np.array([[0, 0, 20.05]]), Sphere(20.0)), [[0, 0, -0.05]])


def test_axial_projection_cylinder_has_no_y_error():
    rng = np.random.default_rng(2)
    th = rng.uniform(0.1, np.pi - 0.1, 200)
    r = 15.0 + rng.uniform(-0.2, 0.2, 200)
    p = np.stack([r * np.cos(th), rng.uniform(-30, 30, 200), r * np.sin(th)], 1)
    e = targets.point_errors(p, Cylinder(15.0))
    assert np.all(e[:, 1] == 0)
    assert np.allclose(e[:, 0], (15.0 - r) * np.cos(th)) and np.allclose(e[:, 2], (15.0 - r) * np.sin(th))


def test_fitted_centre_recovers_shifted_sphere():
    c = np.array([1.5, -2.0, 0.7])
    rng = np.random.default_rng(3)
    p = sphere_points(20.0, c) + rng.normal(0, 0.005, (500, 3))
    e, used = targets.errors_with_fit(p, Sphere(20.0), fit_center=True)
    assert np.allclose(used.center, c, atol=0.01) and used.radius == 20.0
    assert np.sqrt(np.mean(e**2)) < 0.01
    e0, used0 = targets.errors_with_fit(p, Sphere(20.0), fit_center=False)
    assert used0 == Sphere(20.0) and np.abs(e0).max() > 1.0
    cf, rf, rms = fitting.fit_sphere(p)
    assert np.allclose(cf, c, atol=0.01) and rf == pytest.approx(20.0, abs=0.01) and rms < 0.01


def test_fitted_cylinder_and_plane_positions():
    rng = np.random.default_rng(4)
    th = rng.uniform(0.2, np.pi - 0.2, 400)
    p = np.stack([12 * np.cos(th) + 0.8, rng.uniform(-20, 20, 400), 12 * np.sin(th) - 0.5], 1)
    e, used = targets.errors_with_fit(p, Cylinder(12.0), fit_center=True)
    assert np.allclose(used.center, [0.8, 0.0, -0.5], atol=1e-6) and np.abs(e).max() < 1e-6
    q = np.c_[rng.uniform(-5, 5, (100, 2)), np.full(100, 0.3)]
    e, used = targets.errors_with_fit(q, Plane(), fit_center=True)
    assert used.point[2] == pytest.approx(0.3) and np.abs(e).max() < 1e-12


def test_circle_fit():
    th = np.linspace(0.3, 2.5, 100)
    xz = np.stack([3 + 25 * np.cos(th), -40 + 25 * np.sin(th)], 1)
    c, r, rms = fitting.fit_circle_2d(xz)
    assert np.allclose(c, [3, -40]) and r == pytest.approx(25.0) and rms < 1e-9


def test_fit_errors():
    with pytest.raises(targets.FitError, match="does not fit"):
        targets.errors_with_fit(sphere_points(20.0), Sphere(30.0), fit_center=True)
    with pytest.raises(fitting.FitError, match="at least 4"):
        fitting.fit_sphere(np.zeros((3, 3)))
    with pytest.raises(fitting.FitError, match="NaN"):
        fitting.fit_sphere(np.array([[0, 0, np.nan]] * 5))
    with pytest.raises(fitting.FitError, match="degenerate"):
        fitting.fit_circle_2d(np.stack([np.arange(10.0), np.zeros(10)], 1))  # collinear
    with pytest.raises(fitting.FitError, match="radius"):
        fitting.fit_sphere_center(sphere_points(5.0), -1.0)
    assert issubclass(targets.FitError, ValueError)


def test_bad_input():
    with pytest.raises(ValueError, match="no points"):
        targets.point_errors(np.zeros((0, 3)), Sphere(20.0))
    with pytest.raises(ValueError, match="NaN"):
        targets.point_errors(np.array([[0, 0, np.nan]]), Sphere(20.0))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        targets.point_errors(np.zeros((4, 2)), Sphere(20.0))
    with pytest.raises(TypeError, match="Sphere, Cylinder or Plane"):
        targets.point_errors(np.zeros((4, 3)), "sphere")
