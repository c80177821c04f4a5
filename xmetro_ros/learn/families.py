"""Model families of the study (DT, SVR, MLP, CatBoost, PointNet), their search spaces and the run profiles.

The scikit-learn families and CatBoost are trained on targets in micrometres (``TARGET_SCALE``) so that SVR's
epsilon and the MLP's initialisation see O(1) numbers; the exported ONNX graphs multiply back to mm.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.stats import loguniform, randint, uniform
from sklearn.neural_network import MLPRegressor
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler
from sklearn.svm import SVR
from sklearn.tree import DecisionTreeRegressor

from ..sim.campaign import pose_grid

__all__ = [
    "FAMILIES",
    "POINTWISE_FAMILIES",
    "PROFILES",
    "TARGET_SCALE",
    "Profile",
    "UnknownFamilyError",
    "check_family",
    "get_profile",
    "make_estimator",
    "search_space",
]

TARGET_SCALE = 1000.0  # mm → µm for the scikit-learn / CatBoost families

POINTWISE_FAMILIES = ("dt", "svr", "mlp", "catboost")
FAMILIES = (*POINTWISE_FAMILIES, "pointnet", "pointnet_multi")
DISPLAY = {"dt": "Decision tree", "svr": "SVM", "mlp": "MLP", "catboost": "CatBoost", "pointnet": "PointNet",
           "pointnet_multi": "PointNet (3-axis, compact)"}


class UnknownFamilyError(ValueError):
    """A model family name that does not exist."""


def check_family(name: str) -> str:
    """``name`` if it is a known model family; UnknownFamilyError otherwise."""
    if name not in FAMILIES:
        raise UnknownFamilyError(f"unknown model family {name!r}; known: {', '.join(FAMILIES)}")
    return name


@dataclass(frozen=True)
class Profile:
    """How much work a training run does. The protocol (100 / 5 × 50 points per cloud) is the same in all."""

    name: str
    n_iter: int  # random-search candidates per family and axis
    cv: int  # folds of the randomized search
    cv_max_points: int  # the search sees at most this many training points (refit uses all)
    catboost_iterations: tuple[int, int]
    mlp_max_iter: int
    pointnet_epochs: int
    pointnet_grid: tuple[tuple[int, ...], ...]  # head layouts tried for the study-layout PointNet
    pointnet_grid_epochs: int
    pointnet_study_block2: tuple[int, ...]
    compact: dict = field(default_factory=dict)
    campaign: dict = field(default_factory=dict)  # arguments for the simulated campaign
    campaign_stride: int = 1  # keep every k-th campaign item (quick profiles)
    n_test_draws: int = 5
    shap_points: int = 300
    shap_background: int = 20


PROFILES: dict[str, Profile] = {
    # For the tests: seconds, not minutes. Small nets, 2-fold search, few clouds.
    "micro": Profile(
        "micro", n_iter=2, cv=2, cv_max_points=600, catboost_iterations=(30, 60), mlp_max_iter=60,
        pointnet_epochs=15, pointnet_grid=((32,),), pointnet_grid_epochs=5, pointnet_study_block2=(32, 64),
        compact={"block1": (16,), "block2": (32,), "head": (16,), "epochs": 40},
        campaign={"sphere_diameters": (45,), "cylinder": False}, campaign_stride=3, n_test_draws=2,
        shap_points=60, shap_background=8,
    ),
    "quick": Profile(
        "quick", n_iter=3, cv=5, cv_max_points=1000, catboost_iterations=(100, 200), mlp_max_iter=80,
        pointnet_epochs=15, pointnet_grid=((64, 32),), pointnet_grid_epochs=5, pointnet_study_block2=(64, 128),
        compact={"block1": (32,), "block2": (64,), "head": (32,), "epochs": 40},
        campaign={"sphere_diameters": (35, 55), "cylinder": False}, campaign_stride=3,
        shap_points=200, shap_background=16,
    ),
    # The study's protocol: every cloud, 5-fold randomized search, study-size PointNet with a head grid search.
    "full": Profile(
        "full", n_iter=5, cv=5, cv_max_points=3000, catboost_iterations=(200, 600), mlp_max_iter=200,
        pointnet_epochs=30, pointnet_grid=((512, 256, 128), (128, 64)), pointnet_grid_epochs=5,
        pointnet_study_block2=(64, 128, 1024),
        compact={"block1": (32,), "block2": (64,), "head": (32,), "epochs": 100},
        campaign={"sphere_diameters": (35, 45, 55), "cylinder": True}, campaign_stride=1,
        shap_points=500, shap_background=10,
    ),
}


def balanced_pose_order() -> list[list[list[float]]]:
    """``pose_grid()`` reordered for ``pose_mode="cycle"`` over the 27 study configurations: configuration k
    (digits lateral, direction, exposure in base 3) gets grid pose ``9 tz + 3 tx + ty`` with (tz, tx, ty) =
    M (l, d, e) mod 3, M = [[1, 0, 1], [1, 0, 2], [1, 1, 2]] (invertible over GF(3)). In the grid's own order the
    cycle ties the turn to the lateral density and the X tilt to the direction density (e.g. lateral 15/mm never
    at a -90 deg turn); in this order, over the 4 artifacts' shifted cycles, every (setting, pose axis) pair of
    levels occurs 10-14 times (12 = balanced). Lists, not arrays: the campaign arguments stay JSON."""
    grid = pose_grid()
    m = np.array([[1, 0, 1], [1, 0, 2], [1, 1, 2]])
    order = []
    for k in range(len(grid)):
        tz, tx, ty = m @ np.array([k // 9, (k // 3) % 3, k % 3]) % 3
        order.append(int(9 * tz + 3 * tx + ty))
    return [grid[i].tolist() for i in order]


# The shipped default model's campaign ("train where you search", issue 15): the full profile's, each scan from one
# of the rescan recommender's head orientations (cycled, in balanced_pose_order: still 108 scans).
PROFILES["default"] = dataclasses.replace(
    PROFILES["full"], name="default",
    campaign={**PROFILES["full"].campaign, "poses": balanced_pose_order(), "pose_mode": "cycle"})


# A candidate pose model (issue 29; not shipped): twice the scans (each configuration from two head orientations,
# ``pose_cycles``) and a wider PointNet (64 / 128 / 64). docs/recommend-verified.md has what it does, seed by seed.
PROFILES["default-large"] = dataclasses.replace(
    PROFILES["default"], name="default-large",
    compact={"block1": (64,), "block2": (128,), "head": (64,), "epochs": 100},
    campaign={**PROFILES["default"].campaign, "pose_cycles": 2})


def get_profile(name: str | Profile) -> Profile:
    """The training profile called ``name`` (a Profile is returned as is); KeyError naming the known ones."""
    if isinstance(name, Profile):
        return name
    if name not in PROFILES:
        raise ValueError(f"unknown profile {name!r}; known: {', '.join(PROFILES)}")
    return PROFILES[name]


def make_estimator(family: str, seed: int, profile: Profile, threads: int = 1) -> Any:
    """A fresh, unfitted estimator of a point-wise family (targets in µm)."""
    check_family(family)
    if family == "dt":
        return DecisionTreeRegressor(random_state=seed)
    if family == "svr":
        return make_pipeline(StandardScaler(), SVR(kernel="rbf", cache_size=500))
    if family == "mlp":
        return make_pipeline(
            StandardScaler(),
            MLPRegressor(max_iter=profile.mlp_max_iter, early_stopping=True, n_iter_no_change=15,
                         learning_rate_init=1e-3, random_state=seed),
        )
    if family == "catboost":
        from catboost import CatBoostRegressor

        return CatBoostRegressor(random_seed=seed, verbose=0, thread_count=threads, allow_writing_files=False,
                                 loss_function="MAE")
    raise UnknownFamilyError(f"{family!r} is not a point-wise family (use the PointNet trainer)")


def search_space(family: str, profile: Profile) -> dict[str, Any]:
    """Randomized-search distributions (names as in ``make_estimator``'s estimator)."""
    check_family(family)
    if family == "dt":
        return {"max_depth": randint(3, 25), "min_samples_leaf": randint(1, 40), "max_features": [None, 0.5, 0.8]}
    if family == "svr":
        return {"svr__C": loguniform(1.0, 1e3), "svr__gamma": loguniform(1e-3, 1.0),
                "svr__epsilon": loguniform(0.05, 5.0)}
    if family == "mlp":
        sizes = [(16,), (32,)] if profile.name == "micro" else [(32,), (64,), (64, 64), (128, 64)]
        return {"mlpregressor__hidden_layer_sizes": sizes,
                "mlpregressor__alpha": loguniform(1e-6, 1e-2),
                "mlpregressor__learning_rate_init": loguniform(3e-4, 3e-3)}
    if family == "catboost":
        lo, hi = profile.catboost_iterations
        return {"depth": randint(4, 9), "learning_rate": loguniform(0.02, 0.3), "l2_leaf_reg": uniform(1.0, 9.0),
                "iterations": randint(lo, hi + 1)}
    raise UnknownFamilyError(f"{family!r} has no randomized search space (PointNet uses a head grid)")


def validate_space(space: dict[str, Any], family: str) -> None:
    """Raise ValueError if a distribution cannot be sampled (empty list, bad object)."""
    rng = np.random.default_rng(0)
    for k, v in space.items():
        if hasattr(v, "rvs"):
            try:
                v.rvs(random_state=rng)
            except Exception as e:
                raise ValueError(f"{family}: search parameter {k!r} cannot be sampled: {e}") from e
        elif isinstance(v, (list, tuple)):
            if len(v) == 0:
                raise ValueError(f"{family}: search parameter {k!r} has an empty list of values")
        else:
            raise ValueError(f"{family}: search parameter {k!r} must be a list or a scipy distribution, got {v!r}")
