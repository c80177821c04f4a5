"""The study's evaluation protocol on a point table (study §3.6), plus a split by cloud.

* point split (the study's): per cloud, 100 random training points; five test draws of 50 points per cloud, each
  drawn without replacement from the cloud's points not used for training.
* cloud split (ours): whole scanner *configurations* are held out (all clouds taken with them), so no neighbour of
  a test point is in training; the model is trained once on 100 points per training cloud and tested on five draws
  of 50 points per held-out cloud. Point-level splits leak neighbouring points (and the cloud's settings).

Metrics: MAE (mm) and R², per axis, mean ± std over the draws.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["SETTING_FEATURES", "Split", "cloud_split", "mae", "r2", "study_split", "summarize"]

SETTING_FEATURES = ("lateral_density", "direction_density", "exposure_time")


@dataclass
class Split:
    """Indices into a table: one training set and ``len(test)`` test draws."""

    name: str
    train: np.ndarray
    test: list[np.ndarray]
    held_out_groups: list | None = None


def _clouds(cloud_id: np.ndarray) -> list[np.ndarray]:
    cloud_id = np.asarray(cloud_id)
    if cloud_id.size == 0:
        raise ValueError("the data set has no points")
    order = np.argsort(cloud_id, kind="stable")
    bounds = np.flatnonzero(np.diff(cloud_id[order])) + 1
    return np.split(order, bounds)


def study_split(cloud_id: np.ndarray, n_train: int = 100, n_test: int = 50, n_draws: int = 5, seed: int = 0) -> Split:
    """The study's split (see module doc). Raises ValueError naming a cloud with too few points."""
    rng = np.random.default_rng(seed)
    train: list[np.ndarray] = []
    draws: list[list[np.ndarray]] = [[] for _ in range(n_draws)]
    for members in _clouds(cloud_id):
        if len(members) < n_train + n_test:
            raise ValueError(
                f"cloud {np.asarray(cloud_id)[members[0]]!r} has {len(members)} points; the protocol needs at "
                f"least {n_train} + {n_test}"
            )
        perm = rng.permutation(members)
        train.append(perm[:n_train])
        rest = perm[n_train:]
        for d in range(n_draws):
            draws[d].append(rng.choice(rest, n_test, replace=False))
    return Split("point", np.sort(np.concatenate(train)), [np.sort(np.concatenate(d)) for d in draws])


def cloud_split(
    cloud_id: np.ndarray,
    config_key: np.ndarray | None = None,
    held_out_fraction: float = 0.2,
    n_train: int = 100,
    n_test: int = 50,
    n_draws: int = 5,
    seed: int = 0,
) -> Split:
    """Hold out whole configurations (``config_key`` per point; default: each cloud its own group)."""
    rng = np.random.default_rng(seed + 7919)
    cloud_id = np.asarray(cloud_id)
    key = cloud_id if config_key is None else np.asarray(config_key)
    groups = np.unique(key)
    if len(groups) < 2:
        raise ValueError("the cloud split needs at least two configurations (or clouds)")
    n_out = min(len(groups) - 1, max(1, round(held_out_fraction * len(groups))))
    held = set(rng.choice(groups, n_out, replace=False).tolist())
    train: list[np.ndarray] = []
    draws: list[list[np.ndarray]] = [[] for _ in range(n_draws)]
    for members in _clouds(cloud_id):
        if len(members) < max(n_train, n_test):
            raise ValueError(f"cloud {cloud_id[members[0]]!r} has only {len(members)} points")
        if key[members[0]] in held:
            for d in range(n_draws):
                draws[d].append(rng.choice(members, n_test, replace=False))
        else:
            train.append(rng.choice(members, n_train, replace=False))
    return Split("cloud", np.sort(np.concatenate(train)), [np.sort(np.concatenate(d)) for d in draws],
                 held_out_groups=sorted(held))


def config_keys(X: np.ndarray, feature_names: list[str]) -> np.ndarray | None:
    """One integer per distinct settings configuration (from the setting features), or None if absent."""
    cols = [feature_names.index(n) for n in SETTING_FEATURES if n in feature_names]
    if not cols:
        return None
    _, inv = np.unique(np.round(np.asarray(X)[:, cols], 6), axis=0, return_inverse=True)
    return inv.reshape(-1)


def mae(y: np.ndarray, p: np.ndarray) -> float:
    """Mean absolute error of predictions ``p`` against targets ``y`` (their unit)."""
    return float(np.mean(np.abs(np.asarray(y, np.float64) - np.asarray(p, np.float64))))


def r2(y: np.ndarray, p: np.ndarray) -> float:
    """Coefficient of determination R² of ``p`` against ``y`` (0 when ``y`` is constant)."""
    y = np.asarray(y, np.float64)
    ss = float(np.sum((y - y.mean()) ** 2))
    return float(1.0 - np.sum((y - np.asarray(p, np.float64)) ** 2) / ss) if ss > 0 else float("nan")


def summarize(values: list[float]) -> dict[str, Any]:
    """Mean, population std and the values themselves of the per-draw metrics."""
    v = np.asarray(values, np.float64)
    return {"mean": float(v.mean()), "std": float(v.std(ddof=0)), "draws": [float(x) for x in v]}
