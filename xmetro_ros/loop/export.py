"""Export the loop's augmented model (current features + the added ones) with LEARN's ``export_model_set``, so that
``ModelSet.load`` and the node use it; the card lists the new feature (e.g. ``field_intensity``, read by the node
from the PointCloud2 field ``intensity``)."""

from __future__ import annotations

from pathlib import Path

from .data import LoopData, LoopInputError
from .run import LoopResult

__all__ = ["export_loop_model"]


def export_loop_model(result: LoopResult, data: LoopData, out_dir: str | Path) -> Path:
    """Write the augmented model set into ``out_dir`` (``result.model``, or with a given model the family retrained
    on the augmented features). Every feature must be computable by the feature
    registry (study features and ``field_<name>``); derived loop candidates are not registry features → error."""
    from ..judge.features import REGISTRY
    from ..learn.train import export_model_set

    if not result.added_features:
        raise LoopInputError("nothing to export: no feature was added")
    missing = [n for n in result.feature_names if n not in REGISTRY]
    if missing:
        raise LoopInputError(f"features {missing} are not in the feature registry; the node could not compute them")
    if result.X is None:
        raise LoopInputError("the loop result holds no feature table to export from")
    X_train = result.X[result.train_mask]
    model = result.model
    if model is None:
        # With a given model the loop corrected it with a residual model; what ships is the family retrained on
        # the augmented features (same rows the corrector saw).
        from .model import fit_family

        cfg = result.report["config"]
        model = fit_family(cfg["family"], X_train, data.errors[result.train_mask], list(result.feature_names),
                           seed=cfg["seed"], iterations=cfg["iterations"])
    return export_model_set(
        model.models, out_dir, feature_names=list(result.feature_names), X_train=X_train,
        card_extra={"loop": {"added_features": result.added_features, "source": data.source,
                             "after": result.report["after"]}},
        model_id=f"loop-{model.family}-" + "-".join(result.added_features), check_X=X_train[:64],
    )
