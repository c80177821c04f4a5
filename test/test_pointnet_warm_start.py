"""PointNetRegressor(warm_start=...): fine-tuning starts from the given network (weights and normalisation), never
modifies it, and refuses a network of other features or heads."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from xmetro_ros.learn.pointnet import PointNetConfig, PointNetRegressor

CFG = {"block1": (8,), "block2": (16,), "head": (8,), "set_size": 10, "sigma_head": True}


def _data(seed: int, shift: float = 0.0):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(400, 3)).astype(np.float32) + shift
    y = np.stack([0.01 * X[:, 0], 0.02 * X[:, 1] ** 2, -0.01 * X[:, 2]], 1)
    return X, y, np.repeat(np.arange(8), 50)


def test_warm_start_starts_from_the_prior_and_leaves_it_intact():
    X, y, g = _data(0)
    prior = PointNetRegressor(PointNetConfig(**CFG, epochs=5), seed=0).fit(X, y, g)
    before = {k: v.clone() for k, v in prior.module_.state_dict().items()}
    X2, y2, g2 = _data(1, shift=0.5)  # other data: a fresh fit would take other normalisation statistics
    # lr = 0: the fine-tuned network IS the prior (weights and x / y normalisation), whatever data it sees
    frozen = PointNetRegressor(PointNetConfig(**CFG, epochs=1, lr=0.0), seed=3, warm_start=prior.module_)
    frozen.fit(X2, y2, g2)
    np.testing.assert_array_equal(frozen.predict(X2, g2, seed=1), prior.predict(X2, g2, seed=1))
    tuned = PointNetRegressor(PointNetConfig(**CFG, epochs=3), seed=3, warm_start=prior.module_).fit(X2, y2, g2)
    assert not np.array_equal(tuned.predict(X2, g2, seed=1), prior.predict(X2, g2, seed=1))
    for k, v in prior.module_.state_dict().items():  # the prior itself is untouched
        assert torch.equal(v, before[k]), k
    # a fresh fit on the same data normalises with the data's own statistics
    fresh = PointNetRegressor(PointNetConfig(**CFG, epochs=1, lr=0.0), seed=3).fit(X2, y2, g2)
    assert not torch.allclose(fresh.module_.x_mean, prior.module_.x_mean)


def test_warm_start_refuses_another_network():
    X, y, g = _data(0)
    prior = PointNetRegressor(PointNetConfig(**CFG, epochs=1), seed=0).fit(X, y, g)
    with pytest.raises(ValueError, match="other features or heads"):
        PointNetRegressor(PointNetConfig(**CFG, epochs=1), warm_start=prior.module_).fit(X[:, :2], y, g)
    with pytest.raises(ValueError, match="other features or heads"):
        PointNetRegressor(PointNetConfig(**{**CFG, "sigma_head": False}, epochs=1),
                          warm_start=prior.module_).fit(X, y, g)
