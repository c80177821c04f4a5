"""Compiled grid pre-processing (xmetro_ros.preprocess.grid_kernels) against the numpy path it replaces:
bit-identical outlier masks, normals, quality, kept points and orientation on simulated organized scans with NaN
holes and outliers."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage

from xmetro_ros import preprocess as pp
from xmetro_ros.preprocess import grid as pp_grid
from xmetro_ros.preprocess import grid_kernels as gk
from xmetro_ros.preprocess import points as pp_points
from xmetro_ros.scan.artifacts import Cylinder, Plane, Sphere
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim import simulate_scan


@pytest.fixture(scope="module")
def scanner():
    return ScannerModel.load()


def bits(a: np.ndarray) -> np.ndarray:
    """The bit patterns of a float array (NaN payloads and signed zeros compared too)."""
    a = np.ascontiguousarray(a)
    return a.view(np.uint32 if a.dtype == np.float32 else np.uint64)


def damaged(scan, seed: int, holes: float = 0.03, n_out: int = 200, dtype=np.float64):
    """The scan with random NaN holes (single cells and a block), points displaced 0.1-3 mm (outliers) and a lone
    return in an empty corner, cast to ``dtype``."""
    rng = np.random.default_rng(seed)
    g = np.array(scan.points, dtype=np.float64)
    h, w = g.shape[:2]
    g[rng.random((h, w)) < holes] = np.nan
    g[h // 3: h // 3 + 4, w // 2: w // 2 + 7] = np.nan
    valid = np.flatnonzero(np.isfinite(g.reshape(-1, 3)).all(axis=1))
    idx = rng.choice(valid, min(n_out, len(valid) // 10), replace=False)
    flat = g.reshape(-1, 3)
    flat[idx] += rng.normal(0, 1, (len(idx), 3)) * rng.uniform(0.1, 3.0, (len(idx), 1))
    g[0, 0] = [1e3, 1e3, 0.0]
    g[0, 1] = g[1, 0] = np.nan
    return replace(scan, points=g.astype(dtype))


SCANS = [
    (Sphere(17.5), ScanSettings(10.0, 4.0, 0.5), 0),
    (Sphere(27.5), ScanSettings(6.0, 3.0, 2.0), 1),
    (Cylinder(15.0), ScanSettings(15.0, 5.0, 0.1), 2),
    (Plane(), ScanSettings(10.0, 3.0, 0.5), 3),
]


@pytest.fixture(scope="module", params=range(len(SCANS)), ids=["sphere17", "sphere27", "cylinder", "plane"])
def sim_scan(request, scanner):
    art, settings, seed = SCANS[request.param]
    return damaged(simulate_scan(art, settings, scanner=scanner, seed=seed), seed)


@pytest.mark.parametrize("size", [1, 3, 5, 9])
def test_box_mean_is_scipy_uniform_filter(size):
    rng = np.random.default_rng(size)
    for shape in ((37, 53), (2, 40), (40, 1), (4, 4)):
        a = rng.standard_normal(shape).astype(np.float32)
        a[rng.random(shape) < 0.3] = 0
        a[rng.random(shape) < 0.1] = -0.0
        assert np.array_equal(bits(gk.box_mean(a, size)), bits(ndimage.uniform_filter(a, size, mode="constant")))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_outlier_mask_and_normal_planes_bit_identical(sim_scan, dtype):
    g = np.asarray(sim_scan.points, dtype=dtype)
    x, y, z, valid = pp_grid._planes(g)
    x2, y2, z2, valid2, n = gk.planes(g)
    assert n == int(valid.sum()) and np.array_equal(valid, valid2)
    assert all(np.array_equal(bits(a), bits(b)) for a, b in ((x, x2), (y, y2), (z, z2)))
    for scale_window, factor in ((9, 6.0), (5, 3.0)):
        args = (0.05, factor, 20.0, scale_window)
        m_np = pp_grid._grid_outliers_planes(x, y, z, valid, *args)
        m_nb = pp_grid._grid_outlier_mask(x, y, z, valid, *args, "numba")
        assert m_np.any() and np.array_equal(m_np, m_nb)
    for window in (1, 3, 5, 7):
        ref = pp_grid._grid_normals_planes(x, y, z, valid, window)[:4]
        got = gk.grid_normals_planes(x, y, z, valid, window)
        for a, b in zip(ref, got, strict=True):
            assert np.array_equal(bits(a), bits(b)), window


@pytest.mark.parametrize("remove", [True, False])
def test_prepare_scan_bit_identical(sim_scan, scanner, remove):
    for dtype in (np.float64, np.float32):
        scan = replace(sim_scan, points=np.asarray(sim_scan.points, dtype=dtype))
        for window in (5, 3):
            a = pp.prepare_scan(scan, pp.PreprocessConfig(grid_backend="numpy", grid_window=window), remove=remove,
                                scanner=scanner)
            b = pp.prepare_scan(scan, pp.PreprocessConfig(grid_backend="numba", grid_window=window), remove=remove,
                                scanner=scanner)
            assert len(a.outlier) > 0
            assert np.array_equal(a.outlier, b.outlier) and np.array_equal(a.index, b.index)
            assert a.points.dtype == b.points.dtype == np.float64 and np.array_equal(a.points, b.points)
            assert b.normals.dtype == np.float32 and b.normal_quality.dtype == np.float32
            assert np.array_equal(bits(a.normals), bits(b.normals))
            assert np.array_equal(bits(a.normal_quality), bits(b.normal_quality))
            assert np.array_equal(a.geometry.L, b.geometry.L)
            if not remove:  # the lone return in the corner is kept, with a low-quality normal
                assert a.index[0] == 0 and b.normal_quality[0] < 0.3
            assert a.meta == b.meta


def test_public_functions_take_the_backend(sim_scan):
    g = sim_scan.points
    assert np.array_equal(pp.grid_outliers(g, backend="numpy"), pp.grid_outliers(g, backend="numba"))
    (na, qa), (nb, qb) = pp.grid_normals(g, backend="numpy"), pp.grid_normals(g, backend="numba")
    assert np.array_equal(bits(na), bits(nb)) and np.array_equal(bits(qa), bits(qb))
    flat, _, idx = replace(sim_scan, points=g).flat()
    ra = pp.estimate_normals(flat, grid_shape=sim_scan.shape, grid_index=idx, grid_backend="numpy")
    rb = pp.estimate_normals(flat, grid_shape=sim_scan.shape, grid_index=idx, grid_backend="numba")
    assert all(np.array_equal(bits(a), bits(b)) for a, b in zip(ra, rb, strict=True))
    with pytest.raises(pp.PreprocessError, match="backend"):
        pp.grid_outliers(g, backend="fortran")
    with pytest.raises(pp.PreprocessError, match="grid_backend"):
        pp.PreprocessConfig(grid_backend="fortran")


def test_orient_rows_matches_numpy_rules():
    rng = np.random.default_rng(5)
    n = rng.standard_normal((5000, 3)).astype(np.float32)
    n[::7] = np.nan
    n[3] = [np.inf, 0, 0]
    ref = rng.standard_normal((5000, 3)).astype(np.float32)
    ref[10] = n[10] = [1.0, 0.0, 0.0]
    ref[11], n[11] = [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]  # perpendicular: d = 0 keeps the sign
    q = rng.random(5000).astype(np.float32)
    # the numpy rules (prepare_scan): undefined → ref with quality 0, then pp._orient
    n_np, q_np = n.copy(), q.copy()
    bad = ~np.isfinite(n_np).all(axis=1)
    n_np[bad], q_np[bad] = ref[bad], 0
    pp_points._orient(n_np, None, ref)
    gk.orient_rows(n, q, ref)
    assert np.array_equal(bits(n), bits(n_np)) and np.array_equal(bits(q), bits(q_np))
    assert np.array_equal(n[11], [1.0, 0.0, 0.0])


def test_warm_up_compiles_every_kernel():
    assert gk.warm_up() >= 0
    for kernel in (gk._planes, gk._offsets_nearest, gk._spacing_sample, gk._outlier_mask, gk._kept,
                   gk._normals_planes, gk._orient_rows, gk._box):
        assert kernel.signatures, kernel
