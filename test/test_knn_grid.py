"""The compiled grid kNN (xmetro_ros.preprocess.knn_grid) against scipy's cKDTree: the same distances to the bit,
neighbours that are really at those distances, on fuzzed clouds (planes, lines, clusters with far outliers, tiny
clouds, k up to the number of points) and on a simulated scan; the same result at any thread count."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from xmetro_ros.compute import threads
from xmetro_ros.preprocess.knn_grid import knn_grid


def _by_point(points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """knn_grid's rows put back in point order."""
    d, i, q = knn_grid(points, k)
    assert sorted(q.tolist()) == list(range(len(points)))  # every point queried once
    out_d, out_i = np.empty_like(d), np.empty_like(i)
    out_d[q], out_i[q] = d, i
    return out_d, out_i


def _check_against_tree(points: np.ndarray, k: int) -> None:
    d, i = _by_point(points, k)
    ref_d, _ = cKDTree(points).query(points, k=k)
    ref_d = ref_d.reshape(len(points), k)
    assert np.array_equal(d, ref_d)  # the same k smallest distances, bit for bit, ascending
    # each neighbour really lies at its distance (the same formula as scipy: sum of squares, then the root)
    e = points[i] - points[:, None, :]
    assert np.array_equal(np.sqrt(e[..., 0] ** 2 + e[..., 1] ** 2 + e[..., 2] ** 2), d)
    assert all(len(set(row)) == k for row in i.tolist())  # k distinct points
    assert np.array_equal(i[:, 0], np.arange(len(points)))  # distinct points: each is its own nearest


@st.composite
def clouds(draw) -> np.ndarray:
    kind = draw(st.sampled_from(["gauss", "plane", "line", "clusters"]))
    n = draw(st.integers(1, 300))
    seed = draw(st.integers(0, 2**31 - 1))
    scale = draw(st.sampled_from([1e-3, 1.0, 50.0, 1e4]))
    rng = np.random.default_rng(seed)
    if kind == "gauss":
        p = rng.normal(size=(n, 3))
    elif kind == "plane":
        p = np.c_[rng.uniform(0, 10, (n, 2)), np.zeros(n)] @ rng.normal(size=(3, 3))
    elif kind == "line":
        p = np.outer(rng.uniform(0, 10, n), rng.normal(size=3))
    else:  # dense clusters plus a few points far away: rings of empty cells to cross
        centres = rng.uniform(-100, 100, (3, 3))
        p = centres[rng.integers(0, 3, n)] + rng.normal(scale=0.1, size=(n, 3))
        p[: max(1, n // 50)] = rng.uniform(-1000, 1000, (max(1, n // 50), 3))
    p = np.unique(p * scale, axis=0)  # distinct points, as the unorganized path passes them
    return p


@settings(max_examples=150, deadline=None)
@given(p=clouds(), frac=st.floats(0.0, 1.0))
def test_grid_knn_equals_the_kd_tree_on_fuzzed_clouds(p, frac):
    k = 1 + int(frac * (min(len(p), 25) - 1))
    _check_against_tree(p, k)


def test_grid_knn_equals_the_kd_tree_on_a_scan_at_any_thread_count():
    from xmetro_ros.preprocess.points import dedupe
    from xmetro_ros.scan.artifacts import Sphere
    from xmetro_ros.scan.scanner import ScanSettings
    from xmetro_ros.sim import simulate_scan

    s = simulate_scan(Sphere(20.0, np.zeros(3)), ScanSettings(6.0, 3.0, 0.5), seed=3)
    p = s.flat()[0].astype(np.float64)
    p = p[np.isfinite(p).all(axis=1)]
    p = np.ascontiguousarray(p[dedupe(p)[0]])
    assert len(p) > 5000
    _check_against_tree(p, 20)
    before = threads.budget()
    try:
        runs = []
        for n in (1, 2):
            threads.use_threads(n)
            runs.append(knn_grid(p, 20))
    finally:
        threads.use_threads(before)
    assert all(np.array_equal(a, b) for a, b in zip(*runs, strict=True))


def test_a_cloud_one_cell_size_cannot_fit_goes_to_the_tree(monkeypatch):
    """A dense scan beside a sparse background (the average point's cell ~80× the target): the tree answers, with
    the same contract; the scan alone stays on the grid."""
    from xmetro_ros.preprocess import knn_grid as kg
    from xmetro_ros.scan.artifacts import Sphere
    from xmetro_ros.scan.scanner import ScanSettings
    from xmetro_ros.sim import simulate_scan

    s = simulate_scan(Sphere(20.0, np.zeros(3)), ScanSettings(6.0, 3.0, 2.0), seed=2)
    scan = s.flat()[0].astype(np.float64)
    scan = np.unique(scan[np.isfinite(scan).all(axis=1)], axis=0)
    rng = np.random.default_rng(0)
    background = np.c_[rng.uniform(-500, 500, (20000, 2)), np.full(20000, -300.0)]
    used = []
    monkeypatch.setattr(kg, "_knn_tree", lambda p, k, f=kg._knn_tree: used.append(len(p)) or f(p, k))
    _check_against_tree(scan, 20)
    assert used == []
    both = np.r_[scan, background]
    _check_against_tree(both, 20)
    assert used == [len(both)]
    assert kg.grid_fits(np.full(100, 16), 20) and not kg.grid_fits(np.r_[np.ones(1000), [20000]], 20)


def test_grid_knn_refuses_a_k_beyond_the_points():
    with pytest.raises(ValueError, match=r"k must be in 1\.\.3"):
        knn_grid(np.eye(3), 4)
    with pytest.raises(ValueError, match="k must be in"):
        knn_grid(np.eye(3), 0)


def test_unorganized_path_gives_the_same_bits_as_with_the_kd_tree(monkeypatch):
    """Outlier mask, normals and quality of the unorganized path on a scan: the same bits with the grid search as
    with scipy's tree as its kNN query (what the path used before)."""
    from xmetro_ros.preprocess import knn
    from xmetro_ros.preprocess import knn_grid as knn_grid_module
    from xmetro_ros.scan.artifacts import Sphere
    from xmetro_ros.scan.scanner import ScanSettings
    from xmetro_ros.sim import simulate_scan

    s = simulate_scan(Sphere(20.0, np.zeros(3)), ScanSettings(6.0, 3.0, 2.0), seed=1)
    p = s.flat()[0].astype(np.float64)
    p = p[np.isfinite(p).all(axis=1)]
    grid = knn._knn_unorganized(p, 20, 2.0, 1.0, 20)
    monkeypatch.setattr(knn, "_knn", lambda points, k, workers=2: knn_grid_module._knn_tree(points, k))
    tree = knn._knn_unorganized(p, 20, 2.0, 1.0, 20)
    assert (~grid[0]).sum() > 0  # the statistic removed some points: the masks are compared on something
    for a, b in zip(grid, tree, strict=True):
        assert np.array_equal(a, b, equal_nan=True)
