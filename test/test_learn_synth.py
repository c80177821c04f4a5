"""Small synthetic point tables for the learning tests (known drivers per axis, noise, oracle)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from xmetro_ros.judge.features import STUDY_FEATURES

NAMES = list(STUDY_FEATURES)


def synth_table(n_clouds: int = 8, n_pts: int = 200, seed: int = 0, noise_mm: float = 0.002) -> SimpleNamespace:
    """x error driven by N_x (col 3), y by oriCMOS_y (col 9), z by R_y (col 12); settings constant per cloud."""
    rng = np.random.default_rng(seed)
    xs, cid = [], []
    for c in range(n_clouds):
        x = rng.normal(size=(n_pts, len(NAMES))).astype(np.float32)
        x[:, :3] = rng.uniform(0.5, 2.0, 3)
        xs.append(x)
        cid.append(np.full(n_pts, c))
    X, cloud_id = np.concatenate(xs), np.concatenate(cid)
    oracle = np.stack([0.02 * np.tanh(X[:, 3]), 0.01 * X[:, 9], 0.015 * np.sin(X[:, 12])], axis=1)
    y = oracle + rng.normal(scale=noise_mm, size=oracle.shape)
    return SimpleNamespace(X=X, y=y, cloud_id=cloud_id, oracle=oracle, feature_names=NAMES)
