"""The set inference of ``ModelSet`` as it was before issue 13 (gather ``X[idx]`` of the (M, F) rows into set
order, a float64 scatter back, error and σ̂ from the same ONNX runs, chunks of 128 sets), kept verbatim as the
reference the contiguous implementation must reproduce bit for bit (test/test_inference_sets.py) and as the
"before" of bench/bench_uncertainty.py. Functions of a loaded ``ModelSet`` (its sessions and card). One change
since: the σ̂ cap (``ModelSet.log_sigma_max``, card ``uncertainty.sigma_max_mm``), applied to log σ̂ as there."""

from __future__ import annotations

import numpy as np

from xmetro_ros.judge.pointsets import partition_sets

SET_CHUNK = 128


def predict_sets(ms, sets: np.ndarray) -> np.ndarray:
    sets = np.asarray(sets, dtype=np.float32)
    k, n, f = sets.shape
    out = np.empty((k, n, 3))
    for m in ms.members:
        if m.kind == "points":
            out[:, :, m.axes[0]] = m.session.run(None, {"X": sets.reshape(k * n, f)})[0].reshape(k, n)
            continue
        ys = np.empty((k, n, len(m.axes)), np.float32)
        for i in range(0, k, SET_CHUNK):
            ys[i : i + SET_CHUNK] = m.session.run(None, {"X": sets[i : i + SET_CHUNK]})[0]
        out[:, :, list(m.axes)] = ys
    return out


def predict_batch(ms, Xq: np.ndarray) -> np.ndarray:
    Xq = np.asarray(Xq, dtype=np.float32)
    q, p, f = Xq.shape
    out = np.empty((q, p, 3))
    if p == 0:
        return out
    idx, _ = partition_sets(p, ms.set_size, ms.partition_seed)
    sets = Xq[:, idx].reshape(-1, ms.set_size, f)
    ys = predict_sets(ms, sets)
    out[:, idx.reshape(-1)[:p]] = ys.reshape(q, -1, 3)[:, :p]
    return out


def predict(ms, X: np.ndarray) -> np.ndarray:
    X = np.asarray(X, dtype=np.float32)
    ok = np.all(np.isfinite(X), axis=1)
    if ok.all():
        return predict_batch(ms, X[None])[0]
    out = np.full((len(X), 3), np.nan)
    if ok.any():
        out[ok] = predict_batch(ms, X[ok][None])[0]
    return out


def predict_sets_sigma(ms, sets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    sets = np.asarray(sets, dtype=np.float32)
    k, n, f = sets.shape
    out = np.empty((k, n, 3))
    sig = np.ones((k, n, 3))
    for m in ms.members:
        if m.kind == "points":
            out[:, :, m.axes[0]] = m.session.run(None, {"X": sets.reshape(k * n, f)})[0].reshape(k, n)
            continue
        ys = np.empty((k, n, len(m.axes)), np.float32)
        ss = np.empty((k, n, len(m.axes)), np.float32)
        for i in range(0, k, SET_CHUNK):
            res = m.session.run(None, {"X": sets[i : i + SET_CHUNK]})
            ys[i : i + SET_CHUNK] = res[0]
            if m.sigma:
                ss[i : i + SET_CHUNK] = res[1]
        out[:, :, list(m.axes)] = ys
        if m.sigma:
            if ms.log_sigma_max is not None:  # the σ̂ cap (added after this reference was written; card sigma_max_mm)
                ss = np.minimum(ss, ms.log_sigma_max[list(m.axes)])
            sig[:, :, list(m.axes)] = np.exp(ss)
    return out, sig


def _predict_sigma_finite(ms, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = len(X)
    if p == 0:
        return np.empty((0, 3)), np.empty((0, 3))
    idx, _ = partition_sets(p, ms.set_size, ms.partition_seed)
    e, s = predict_sets_sigma(ms, X[idx])
    both = np.empty((p, 6))
    both[idx.reshape(-1)[:p]] = np.concatenate([e, s], axis=-1).reshape(-1, 6)[:p]
    return both[:, :3], both[:, 3:]


def predict_with_sigma(ms, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    X = np.asarray(X, dtype=np.float32)
    ok = np.all(np.isfinite(X), axis=1)
    p = int(ok.sum())
    if p == len(X):
        return _predict_sigma_finite(ms, X)
    err = np.full((len(X), 3), np.nan)
    sig = np.full((len(X), 3), np.nan)
    if p:
        err[ok], sig[ok] = _predict_sigma_finite(ms, X[ok])
    return err, sig


def domain_distance(ms, X: np.ndarray) -> np.ndarray:
    dom = ms.card.get("domain_mv")
    if not dom:
        return np.full(len(X), np.nan)
    w = np.asarray(dom["whiten"], np.float64) / float(dom["threshold"])
    w, b = w.astype(np.float32), (np.asarray(dom["mean"], np.float64) @ w).astype(np.float32)
    # The one arithmetic ModelSet uses since 0.7.4 (set_kernels.whitened_norm), written out in numpy: every row alone,
    # z_j = Σ_i x_i·w_ij over i ascending, then Σ_j (z_j − b_j)² over j ascending, float32, each product and sum
    # rounded on its own (numpy's element-wise float32 operations; no fused multiply-add), then the square root.
    X = np.asarray(X, np.float32)
    z = np.zeros((len(X), w.shape[1]), np.float32)
    for i in range(X.shape[1]):
        z += X[:, i:i + 1] * w[i]
    s = np.zeros(len(X), np.float32)
    for j in range(w.shape[1]):
        zj = z[:, j] - b[j]
        s += zj * zj
    return np.sqrt(s)


def domain_distance_einsum(ms, X: np.ndarray) -> np.ndarray:
    """The domain distance as 0.7.2-0.7.3 computed it (numpy's einsum loops; other last bits than
    :func:`domain_distance`): what bench/bench_uncertainty.py times the compiled pass against."""
    dom = ms.card["domain_mv"]
    w = np.asarray(dom["whiten"], np.float64) / float(dom["threshold"])
    w, b = w.astype(np.float32), (np.asarray(dom["mean"], np.float64) @ w).astype(np.float32)
    z = np.einsum("ij,jk->ik", np.asarray(X, np.float32), w)
    z -= b
    return np.sqrt(np.einsum("ij,ij->i", z, z))


def predict_with_uncertainty(ms, X: np.ndarray, distance=domain_distance
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(errors, U, sigma, domain_distance) as ``ModelSet.predict_with_uncertainty`` computed them (``distance``:
    the domain distance's implementation)."""
    X = np.asarray(X, dtype=np.float32)
    err, sig = predict_with_sigma(ms, X)
    # The one change to the verbatim reference: a card calibrated per condition (incidence x exposure) has a
    # multiplier per row, looked up by the ModelSet (judge/conditions.py); the arithmetic below is the reference's.
    mult = ms.multipliers(X)
    dist = distance(ms, X)
    with np.errstate(invalid="ignore"):
        widen = np.where(dist > 1.0, dist, 1.0)
    floor = float(ms.card["uncertainty"].get("sigma_floor_mm", 0.0))
    U = sig + floor
    U *= mult
    U *= widen[:, None]
    return err, U, sig, dist
