"""How a cloud's points are grouped into PointNet sets at inference (numpy only: the node never imports torch).

A whole scan is split deterministically into sets of ``set_size`` points by a seeded permutation; a last, shorter
set is padded by repeating its own points, which leaves a max-pooled global feature unchanged, and only the real
entries are kept. ``inference.ModelSet``, the explainer and the exporter share this one definition (it is also
re-exported by ``learn.pointnet``).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

__all__ = ["partition_sets", "set_membership", "set_order"]


def partition_sets(n_points: int, set_size: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic partition of ``n_points`` points into sets of ``set_size``.

    Returns (idx (K, set_size) int64 point indices, real (K, set_size) bool): each point appears exactly once as a
    real entry; the last set is padded by cycling through its own points (max-pool invariant).
    """
    if n_points <= 0:
        raise ValueError("cannot partition an empty set of points")
    if set_size <= 0:
        raise ValueError(f"set_size must be positive, got {set_size}")
    perm = np.random.default_rng(seed).permutation(n_points)
    k = -(-n_points // set_size)
    idx = np.empty(k * set_size, dtype=np.int64)
    idx[:n_points] = perm
    real = np.zeros(k * set_size, dtype=bool)
    real[:n_points] = True
    rem = n_points - (k - 1) * set_size
    if rem < set_size:
        last = perm[(k - 1) * set_size :]
        idx[n_points:] = last[np.arange(set_size - rem) % rem]
    return idx.reshape(k, set_size), real.reshape(k, set_size)


def set_membership(n_points: int, set_size: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The partition of :func:`partition_sets` and, for every point, the index of the set it is a real entry of:
    (idx (K, set_size), set_of (n_points,) int64)."""
    idx, _ = partition_sets(n_points, set_size, seed)
    set_of = np.empty(n_points, np.int64)
    set_of[idx.reshape(-1)[:n_points]] = np.arange(n_points) // set_size  # real entries come first, set by set
    return idx, set_of


@lru_cache(maxsize=8)
def set_order(n_points: int, set_size: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The partition of :func:`partition_sets` as two flat index arrays, cached (read-only): the partition depends
    only on the point count, and a stream of scans of one scanner repeats a few counts (the permutation of 180k
    points costs ~3 ms).

    Returns (order (K * set_size,) int64: the point at each slot of the sets laid end to end, padding included, so
    ``X[order].reshape(K, set_size, F)`` are the sets; pos (n_points,) int64: the slot of each point's real entry,
    so ``Y[pos]`` reads per-slot outputs Y (K * set_size, ...) back in point order).
    """
    idx, _ = partition_sets(n_points, set_size, seed)
    order = idx.reshape(-1)
    pos = np.empty(n_points, np.int64)
    pos[order[:n_points]] = np.arange(n_points)  # real entries come first, in slot order
    order.flags.writeable = False
    pos.flags.writeable = False
    return order, pos
