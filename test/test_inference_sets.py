"""Contiguous PointNet sets (issue 13): ``ModelSet`` gathers the finite rows straight into set order, runs ONNX
Runtime on slices of that buffer and reads the outputs back by the cached partition. Its outputs must be those of
the implementation before (test/reference_inference.py, kept verbatim): bit-identical errors and σ̂ on clouds of
several sizes (a last set padded or not, one point, NaN and inf rows), through every entry point; error and σ̂ from
the same ONNX runs; the domain distance to float32 rounding."""

from __future__ import annotations

import numpy as np
import pytest
import reference_inference as ref
from test_learn_synth import NAMES, synth_table

from xmetro_ros.judge.inference import ModelSet
from xmetro_ros.judge.pointsets import partition_sets, set_order
from xmetro_ros.learn.families import get_profile
from xmetro_ros.learn.train import export_model_set, fit_model

SIZES = (1, 49, 50, 51, 137, 6400, 6449)  # 6400 = 128 sets: one full ONNX chunk; others pad the last set


@pytest.fixture(scope="module")
def default():
    return ModelSet.load()


@pytest.fixture(scope="module")
def features(default):
    """Rows spread around the default model's training mean (some outside its domain), float32."""
    rng = np.random.default_rng(5)
    lo, hi = default.domain
    return (lo + (hi - lo) * rng.uniform(-0.1, 1.1, size=(max(SIZES), len(lo)))).astype(np.float32)


@pytest.fixture(scope="module")
def dt_set(tmp_path_factory):
    """A model set of point-wise members (one decision tree per axis)."""
    t = synth_table(n_clouds=3, n_pts=200, seed=2)
    dts = [fit_model("dt", t.X, t.y[:, a], seed=0, profile=get_profile("micro"), axes=(a,), params={"max_depth": 5})
           for a in range(3)]
    d = export_model_set(dts, tmp_path_factory.mktemp("dt") / "dt", feature_names=NAMES, X_train=t.X,
                         model_id="test-dt-sets")
    return ModelSet.load(d), t.X.astype(np.float32)


def _with_bad_rows(X: np.ndarray, seed: int) -> np.ndarray:
    X = X.copy()
    rng = np.random.default_rng(seed)
    bad = rng.choice(len(X), size=max(1, len(X) // 7), replace=False)
    X[bad[::2], rng.integers(X.shape[1])] = np.nan
    X[bad[1::2], 0] = np.inf
    return X


@pytest.mark.parametrize("n", SIZES)
def test_set_order_is_the_partition(n):
    idx, real = partition_sets(n, 50, 0)
    order, pos = set_order(n, 50, 0)
    np.testing.assert_array_equal(order, idx.reshape(-1))
    np.testing.assert_array_equal(order[pos], np.arange(n))  # every point read back from its real entry
    assert np.all(real.reshape(-1)[pos])
    assert set_order(n, 50, 0)[0] is order  # cached
    with pytest.raises(ValueError):
        order[0] = 1  # read-only: a cached partition cannot be changed by a caller


@pytest.mark.parametrize("n", SIZES)
def test_predict_and_sigma_identical_to_reference(default, features, n):
    for X in (features[:n], _with_bad_rows(features[:n], n)):
        got = default.predict(X)
        want = ref.predict(default, X)
        assert np.array_equal(got, want, equal_nan=True)
        e, s = default.predict_with_sigma(X)
        re, rs = ref.predict_with_sigma(default, X)
        assert np.array_equal(e, re, equal_nan=True) and np.array_equal(s, rs, equal_nan=True)
        assert np.array_equal(e, got, equal_nan=True)
        assert np.isnan(got).any() == (not np.all(np.isfinite(X)))

        u = default.predict_with_uncertainty(X)
        r_err, r_U, r_sig, r_dist = ref.predict_with_uncertainty(default, X)
        for got_, want_ in ((u.errors, r_err), (u.sigma, r_sig), (u.U, r_U), (u.domain_distance, r_dist)):
            assert np.array_equal(got_, want_, equal_nan=True)
        np.testing.assert_array_equal(u.out_of_domain, default.out_of_domain_mv(X, r_dist))


def test_all_rows_nonfinite_and_empty(default, features):
    X = features[:10].copy()
    X[:, 3] = np.nan
    assert np.isnan(default.predict(X)).all()
    e, s = default.predict_with_sigma(X)
    assert e.shape == s.shape == (10, 3) and np.isnan(e).all() and np.isnan(s).all()
    assert default.predict(features[:0]).shape == (0, 3)
    assert default.predict_with_uncertainty(features[:0]).U.shape == (0, 3)


def test_batch_and_sets_identical_to_reference(default, features, dt_set):
    X = features[:137]
    Xq = np.stack([X, X[::-1], X * np.float32(1.01)])
    assert np.array_equal(default.predict_batch(Xq), ref.predict_batch(default, Xq))
    np.testing.assert_array_equal(default.predict_batch(Xq)[0], default.predict(X))
    idx, _ = partition_sets(137, 50, 0)
    sets = X[idx]
    assert np.array_equal(default.predict_sets(sets), ref.predict_sets(default, sets))
    e, s = default.predict_sets_sigma(sets)
    re, rs = ref.predict_sets_sigma(default, sets)
    assert np.array_equal(e, re) and np.array_equal(s, rs)
    # non-contiguous input and a set size other than the card's
    odd = np.asarray(X[: 3 * 7].reshape(3, 7, -1)[:, ::2], np.float64)
    assert np.array_equal(default.predict_sets(odd), ref.predict_sets(default, odd))

    ms, Xd = dt_set  # point-wise members
    for n in (1, 51, 600):
        Xn = _with_bad_rows(Xd[:n], n)
        assert np.array_equal(ms.predict(Xn), ref.predict(ms, Xn), equal_nan=True)
        e, s = ms.predict_with_sigma(Xn)
        re, rs = ref.predict_with_sigma(ms, Xn)
        assert np.array_equal(e, re, equal_nan=True) and np.array_equal(s, rs, equal_nan=True)
    Xq = np.stack([Xd[:60], Xd[60:120]])
    assert np.array_equal(ms.predict_batch(Xq), ref.predict_batch(ms, Xq))


class _Binding:
    """An ONNX Runtime I/O binding that remembers the outputs bound since the last run."""

    def __init__(self, b) -> None:
        self.b = b
        self.names: dict[str, None] = {}

    def bind_output(self, name, *args):
        self.names[name] = None
        return self.b.bind_output(name, *args)

    def __getattr__(self, name):
        return getattr(self.b, name)


class _Counting:
    """An ONNX Runtime session that records the outputs asked for in each run (plain or I/O-bound)."""

    def __init__(self, sess) -> None:
        self.sess = sess
        self.calls: list[tuple[str, ...]] = []

    def run(self, outputs, feed):
        self.calls.append(tuple(outputs) if outputs is not None else ("<all>",))
        return self.sess.run(outputs, feed)

    def io_binding(self):
        return _Binding(self.sess.io_binding())

    def run_with_iobinding(self, io):
        self.calls.append(tuple(io.names))
        io.names = {}
        return self.sess.run_with_iobinding(io.b)

    def __getattr__(self, name):
        return getattr(self.sess, name)


def test_error_and_sigma_come_from_one_run(features):
    ms = ModelSet.load()
    (m,) = ms.members
    assert m.sigma and m.outputs == ("y", "log_sigma")
    m.session = counting = _Counting(m.session)
    n = len(features)
    n_sets = -(-n // ms.set_size)
    n_runs = -(-n_sets // ms.set_chunk)
    ms.predict_with_uncertainty(features)
    assert counting.calls == [("y", "log_sigma")] * n_runs  # one run per chunk gives both outputs
    counting.calls.clear()
    ms.predict(features)
    assert counting.calls == [("y",)] * n_runs


def test_domain_distance_matches_float64(default, features):
    """The float32 GEMM's distances against a float64 computation: float32 rounding (of the features' scale)."""
    dom = default.card["domain_mv"]
    X = _with_bad_rows(features, 3)
    z = (X.astype(np.float64) - np.asarray(dom["mean"])) @ np.asarray(dom["whiten"])
    want = np.sqrt(np.einsum("ij,ij->i", z, z)) / float(dom["threshold"])
    got = default.domain_distance(X)
    assert got.dtype == np.float32
    assert np.isnan(got[np.isnan(X).any(axis=1)]).all()
    fin = np.all(np.isfinite(X), axis=1)
    np.testing.assert_allclose(got[fin], want[fin], rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("n", (1, 137, 6449))
def test_batch_with_uncertainty_is_each_version_alone(default, features, n):
    """The recommender's one-run batch (errors and U of Q versions from the same ONNX runs) gives, bit for bit,
    what ``predict_with_uncertainty`` gives each version on its own (and ``predict_batch``'s two outputs)."""
    X = features[:n]
    Xq = np.stack([X, X[::-1].copy(), X * np.float32(1.01)])
    d, U = default.predict_batch_with_uncertainty(Xq)
    for k in range(len(Xq)):
        r = default.predict_with_uncertainty(Xq[k])
        assert np.array_equal(d[k], r.errors) and np.array_equal(U[k], r.U, equal_nan=True)
    assert np.array_equal(d, default.predict_batch(Xq))
    assert np.array_equal(U, default.predict_batch(Xq, output="uncertainty"), equal_nan=True)


@pytest.mark.parametrize("threads", (2, 5))
def test_runs_side_by_side_give_the_same_bits(default, features, threads):
    """A model set loaded with several threads runs its chunks of sets side by side, in smaller chunks (load
    balance), and its domain distance in row blocks: errors, σ̂, U, the distance and the batch path give exactly
    what one thread gives."""
    par = ModelSet.load(threads=threads)
    assert par.threads == threads and len(range(0, 200, par._chunk(200))) >= 2 * threads  # every thread busy
    assert par._chunk(10**6) == par.set_chunk and default._chunk(200) == default.set_chunk
    X = _with_bad_rows(features, 9)
    one, many = default.predict_with_uncertainty(X), par.predict_with_uncertainty(X)
    for a in ("errors", "sigma", "U", "domain_distance", "out_of_domain"):
        assert np.array_equal(getattr(one, a), getattr(many, a), equal_nan=True), a
    big = np.tile(X, (3, 1))  # 19k rows: several blocks of the distance
    assert np.array_equal(default.domain_distance(big), par.domain_distance(big), equal_nan=True)
    Xq = np.stack([features[:137], features[137:274]])
    for a, b in zip(default.predict_batch_with_uncertainty(Xq), par.predict_batch_with_uncertainty(Xq), strict=True):
        assert np.array_equal(a, b, equal_nan=True)


def test_a_failing_run_on_the_pool_raises_in_the_caller():
    """An ONNX Runtime error inside a pooled run reaches the caller (not lost in a worker thread)."""
    par = ModelSet.load(threads=2)
    bad = np.zeros((300, 50, len(par.feature_names) + 1), np.float32)  # one feature too many
    with pytest.raises(Exception, match=r"(?i)dimension|shape|invalid"):
        par._run_sets(bad, False)


def test_domain_distance_bits_do_not_depend_on_threads_or_neighbours(default, features):
    """The compiled distance (set_kernels.whitened_norm) at 1 and 2 numba threads, and each row alone against the
    same row in a 19k-row batch (blocks of 64 rows split over the threads): the same bits."""
    from conftest import at_one_and_two_numba_threads

    X = np.tile(_with_bad_rows(features, 5), (3, 1))
    one, two = at_one_and_two_numba_threads(lambda: default.domain_distance(X))
    assert np.array_equal(one, two, equal_nan=True)
    rows = [0, 63, 64, 1000, len(X) - 1]
    alone = np.concatenate([default.domain_distance(X[r:r + 1]) for r in rows])
    assert np.array_equal(alone, one[rows], equal_nan=True)
    assert np.isfinite(one).any() and np.isnan(one).any()
