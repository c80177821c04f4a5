"""The judge's thread budget (xmetro_ros.compute.threads, the node's ``threads``): the same scan judged with 1 and
with every thread numba has gives the same bits in every output — deviations, U, flags, decisions, normals,
curvature, the quality summary — for an organized scan, a profile-posed one and an unorganized one; ONNX Runtime's
intra-op threads follow the budget; the budget's default and its bounds; the helper threads of ``parallel_for``
(every item once, errors to the caller, nested calls inline) and the features split into row blocks on them (the
same bits)."""

from __future__ import annotations

import itertools
import threading
from dataclasses import replace

import numpy as np
import pytest

from xmetro_ros.compute import threads as ct
from xmetro_ros.judge.inference import ModelSet
from xmetro_ros.judge.scan_handler import HandlerParams, ScanHandler
from xmetro_ros.preprocess.curvature import mean_curvature
from xmetro_ros.ros.params import PARAMS, onnx_threads
from xmetro_ros.scan.artifacts import Sphere
from xmetro_ros.scan.geometry import RowPoses
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim import simulate_scan

THREADS = sorted({1, ct.max_threads()})


def _judge(scan, threads: int, model: ModelSet, scanner: ScannerModel):
    return ScanHandler(model, scanner, HandlerParams(threads=threads)).process(scan)


def _same(a, b) -> None:
    np.testing.assert_array_equal(a.deviations, b.deviations)
    np.testing.assert_array_equal(a.uncertainty, b.uncertainty)
    np.testing.assert_array_equal(a.flags, b.flags)
    np.testing.assert_array_equal(a.decisions, b.decisions)
    np.testing.assert_array_equal(a.prepared.normals, b.prepared.normals)
    np.testing.assert_array_equal(a.prepared.index, b.prepared.index)
    np.testing.assert_array_equal(a.features, b.features)
    assert a.quality == b.quality


@pytest.fixture(scope="module")
def judged():
    scanner = ScannerModel.load()
    models = {t: ModelSet.load(None, threads=t) for t in THREADS}
    scan = simulate_scan(Sphere(17.5, np.zeros(3)), ScanSettings(10.0, 4.0, 0.5), seed=3)
    return scanner, models, scan


def test_every_output_is_the_same_at_any_thread_count(judged):
    scanner, models, scan = judged
    ref = _judge(scan, 1, models[THREADS[0]], scanner)
    for t in THREADS[1:]:
        _same(ref, _judge(scan, t, models[t], scanner))
    c = [mean_curvature(_judge(scan, t, models[t], scanner).prepared) for t in THREADS]
    for other in c[1:]:
        np.testing.assert_array_equal(c[0], other)


def test_posed_and_unorganized_scans_too(judged):
    scanner, models, scan = judged
    h, w = scan.shape
    r = np.asarray(scan.pose.rotation, float)
    step = 1.0 / float(scan.settings.direction_density)  # mm between profiles, along the head's +Y
    pos = np.asarray(scan.pose.position, float)[None] + np.arange(h)[:, None] * step * r[:, 1][None]
    rows = np.repeat(np.arange(h, dtype=np.int32)[:, None], w, axis=1)
    posed = replace(scan, row_poses=RowPoses(pos, np.repeat(r[None], h, axis=0), rows))
    pts, fields, _ = scan.flat()
    unorg = replace(scan, points=pts, fields=fields, expected_error=None, noise_std=None, injected_outlier=None)
    for s in (posed, unorg):
        ref = _judge(s, 1, models[THREADS[0]], scanner)
        for t in THREADS[1:]:
            _same(ref, _judge(s, t, models[t], scanner))


def test_the_count_is_the_judging_threads_own(judged):
    """numba's count is per calling thread: a judge on another thread sets its own, the caller's is left alone."""
    scanner, models, scan = judged
    import numba

    ct.use_threads(ct.max_threads())
    seen = []
    t = threading.Thread(target=lambda: (_judge(scan, 1, models[THREADS[0]], scanner),
                                         seen.append(numba.get_num_threads())))
    t.start()
    t.join()
    assert seen == [1]
    assert numba.get_num_threads() == ct.max_threads()
    ct.use_threads(0)
    assert numba.get_num_threads() == ct.default_threads()


def test_budget_defaults_and_bounds(monkeypatch):
    assert 1 <= ct.default_threads() <= min(ct.MAX_DEFAULT_THREADS, ct.max_threads())
    assert ct.resolve_threads(0) == ct.default_threads()
    assert ct.resolve_threads(1) == 1
    assert ct.resolve_threads(10_000) == ct.max_threads()
    with pytest.raises(ValueError, match="threads must be >= 0"):
        ct.resolve_threads(-1)
    monkeypatch.setattr(ct, "available_cpus", lambda: 64)
    assert ct.default_threads() == min(ct.MAX_DEFAULT_THREADS, ct.max_threads())
    monkeypatch.setattr(ct, "available_cpus", lambda: 2)  # one core left to the driver, DDS and the executor
    assert ct.default_threads() == 1
    monkeypatch.setattr(ct, "available_cpus", lambda: 1)
    assert ct.default_threads() == 1
    values = {p.name: p.default for p in PARAMS}
    assert values["threads"] == 0 and values["inference_threads"] == 0
    assert onnx_threads(values) == ct.resolve_threads(0)
    assert onnx_threads({**values, "threads": 1}) == 1
    assert onnx_threads({**values, "threads": 1, "inference_threads": 3}) == 3


def test_threading_layer_is_threadsafe(judged):
    """Two judges at once on two threads (the node's worker and a service): numba's workqueue layer would abort the
    process; the threadsafe layer runs both and gives the same bits as one alone."""
    scanner, models, scan = judged
    import numba

    ref = _judge(scan, 0, models[THREADS[-1]], scanner)
    out: list = []
    ts = [threading.Thread(target=lambda: out.append(_judge(scan, 0, models[THREADS[-1]], scanner)))
          for _ in range(2)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    assert len(out) == 2
    for r in out:
        _same(ref, r)
    assert numba.threading_layer() in ("tbb", "omp")


def test_parallel_for_runs_every_item_once_and_raises_the_first_error():
    """Items run once each, on up to ``threads`` threads (the caller among them); an exception reaches the caller
    after the other items ran; called from a helper (nested) it runs inline."""
    seen: list[tuple[int, str]] = []
    lock = threading.Lock()

    def fn(i: int) -> None:
        with lock:
            seen.append((i, threading.current_thread().name))

    ct.parallel_for(fn, 37, 4)
    assert sorted(i for i, _ in seen) == list(range(37))
    assert len({name for _, name in seen}) <= 4
    seen.clear()
    ct.parallel_for(fn, 5, 1)
    assert {name for _, name in seen} == {threading.current_thread().name}

    def bad(i: int) -> None:
        fn(i)
        if i == 3:
            raise KeyError("item 3")

    seen.clear()
    with pytest.raises(KeyError, match="item 3"):
        ct.parallel_for(bad, 10, 3)
    assert sorted(i for i, _ in seen) == list(range(10))
    inner: list[str] = []

    def outer(i: int) -> None:
        ct.parallel_for(lambda j: inner.append(threading.current_thread().name), 3, 3)

    ct.parallel_for(outer, 4, 2)
    assert len(inner) == 12
    assert ct.block_bounds(100, 1, 10) == [(0, 100)]
    b = ct.block_bounds(100_000, 3, 1000, per_thread=2)
    assert len(b) == 6 and b[0][0] == 0 and b[-1][1] == 100_000 and all(x[1] == y[0] for x, y in itertools.pairwise(b))
    assert ct.block_bounds(1500, 8, 1000) == [(0, 1500)]


def test_feature_row_blocks_give_the_same_bits(judged):
    """Features computed in row blocks on several threads (more than this machine has) are bit for bit the
    one-pass results; a bad normal's error names the cloud's point, not a block's."""
    from xmetro_ros.judge.features import STUDY_FEATURES, FeatureContext, FeatureError, compute_features

    scanner, models, scan = judged
    prep = _judge(scan, 1, models[THREADS[0]], scanner).prepared
    one_ctx, many_ctx = FeatureContext.from_prepared(prep), FeatureContext.from_prepared(prep)
    np.testing.assert_array_equal(compute_features(STUDY_FEATURES, one_ctx, threads=1),
                                  compute_features(STUDY_FEATURES, many_ctx, threads=4))
    for key in ("NdotL", "NdotV", "|NxL|"):  # the blocks' shared intermediates, joined for the flags
        np.testing.assert_array_equal(one_ctx._cache[key], many_ctx._cache[key])
    n = prep.normals.copy()
    n[len(n) - 5] = 0.0
    ctx = replace(FeatureContext.from_prepared(prep), normals=n)
    with pytest.raises(FeatureError, match=f"point {len(n) - 5}:"):
        compute_features(STUDY_FEATURES, ctx, threads=4)
