"""Export the loop's augmented model (current features + the added ones) with LEARN's ``export_model_set``, so that
``ModelSet.load`` and the node use it; the card lists the new feature (e.g. ``field_intensity``, read by the node
from the PointCloud2 field ``intensity``)."""

from __future__ import annotations

from pathlib import Path

from .data import LoopData, LoopInputError
from .run import LoopResult

__all__ = ["export_loop_model"]


def export_loop_model(result: LoopResult, data: LoopData, out_dir: str | Path) -> Path:
    """Write the model set of ``result.model`` into ``out_dir``. Every feature must be computable by the feature
    registry (study features and ``field_<name>``); derived loop candidates are not registry features → error."""
    from ..features import REGISTRY
    from ..learn.train import export_model_set

    if result.model is None:
        raise LoopInputError("nothing to export: no feature was added to a retrained model")
    missing = [n for n in result.feature_names if n not in REGISTRY]
    if missing:
        raise LoopInputError(f"features {missing} are not in the feature registry; the node could not compute them")
    X_train = result.X[result.train_mask]
    return export_model_set(
        result.model.models, out_dir, feature_names=list(result.feature_names), X_train=X_train,
        card_extra={"loop": {"added_features": result.added_features, "source": data.source,
                             "after": result.report["after"]}},
        model_id=f"loop-{result.model.family}-" + "-".join(result.added_features), check_X=X_train[:64],
    )
