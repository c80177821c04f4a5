"""Does seeing mesh parts in training help on other, unseen parts? ``python -m xmetro_ros.parts_seen OUT``.

Two model sets trained with one recipe (``pointnet_multi``, compact layout, the uncertainty experiment's recipe of
:mod:`xmetro_ros.learn.uncertainty_eval` with fewer points): **A** on spheres Ø35 / Ø55 mm and a cylinder r 20 mm
(the 27 study configurations, seed 1), **B** on the same plus the mesh parts ``step`` and ``fillet`` (manufactured,
presented as in the study, every third configuration: 9 each). Each is calibrated (split-conformal by cloud) on its
own training artifacts simulated with seed 2. Both are then judged by :func:`xmetro_ros.parts.study.evaluate_part`
on ``blade`` and ``bowl``, which neither saw (seed 0 and 1, two settings). Needs the ``[train]`` extra (PyTorch).
Writes OUT/seen.json and the two model sets under OUT/models/ (not shipped).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path
from typing import Any

__all__ = ["main", "run"]

EVAL_PARTS = ("blade", "bowl")
TRAIN_PARTS = ("step", "fillet")
EVAL_SETTINGS = ((6.0, 3.0, 0.1), (10.0, 4.0, 0.5))


def _mesh_scans(seed: int, scanner: Any, stride: int = 3) -> list[Any]:
    from ..scan.generated_parts import make_part
    from ..sim import simulate_scan
    from .study import FORM_UM, PRESENTATION

    scans = []
    for k, name in enumerate(TRAIN_PARTS):
        man = make_part(name, form_um=FORM_UM).transformed(PRESENTATION)
        for c, st in enumerate(scanner.study_configurations()[::stride]):
            scans.append(simulate_scan(man, st, scanner=scanner, seed=seed * 1000 + 100 * k + c))
    return scans


def run(out_dir: str | Path, *, epochs: int = 40, train_points: int = 400, seed: int = 0,
        log: Any = print) -> dict[str, Any]:
    """Train A and B, calibrate, evaluate on the unseen parts; returns (and writes) the comparison."""
    import numpy as np

    from ..calibrate.dataset import build_table
    from ..judge.features import STUDY_FEATURES
    from ..judge.inference import ModelSet
    from ..judge.scan_handler import ScanHandler
    from ..learn.families import get_profile
    from ..learn.train import export_model_set, fit_model
    from ..learn.uncertainty import calibrate
    from ..scan.artifacts import Cylinder, Sphere
    from ..scan.scanner import ScannerModel, ScanSettings
    from ..sim.campaign import study_campaign
    from .study import evaluate_part

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sc = ScannerModel.load()
    names = list(STUDY_FEATURES)
    analytic = [Sphere(17.5), Sphere(27.5), Cylinder(20.0)]

    def table(s: int, with_mesh: bool, per_cloud: int) -> Any:
        scans = [it.simulate() for it in study_campaign(sc, seed=s, artifacts=analytic)]
        if with_mesh:
            scans += _mesh_scans(s, sc)
        return build_table(scans, names, max_points_per_cloud=per_cloud, seed=s)

    prof = dataclasses.replace(get_profile("quick"),
                               compact={"block1": (32,), "block2": (64,), "head": (32,), "epochs": int(epochs)})
    result: dict[str, Any] = {"epochs": epochs, "train_points": train_points, "seed": seed,
                              "eval_parts": list(EVAL_PARTS), "train_parts_B": list(TRAIN_PARTS), "models": {}}
    for tag, with_mesh in (("A_analytic", False), ("B_with_parts", True)):
        tr, cal = table(1, with_mesh, train_points), table(2, with_mesh, 200)
        model = fit_model("pointnet_multi", tr.X, tr.y, seed=seed, profile=prof, groups=tr.cloud_id)
        d = export_model_set([model], out / "models" / tag, feature_names=names, X_train=tr.X,
                             check_X=tr.X[tr.cloud_id == 0], model_id=f"parts-{tag}-s{seed}")
        calibrate(d, cal.X, cal.y, cal.cloud_id, cloud_labels=[f"{c['label']}/{c['artifact']['kind']}"
                                                                 for c in cal.clouds])
        handler = ScanHandler(ModelSet.load(d), sc)
        rows = []
        for k, name in enumerate(EVAL_PARTS):
            for j, s in enumerate(EVAL_SETTINGS):
                r = evaluate_part(name, handler, ScanSettings(*s), seed=10 + 2 * k + j, register=False)
                kp = r["cad"]["known_pose"]
                rows.append({"part": name, "settings": list(s), "points": r["points"],
                             "mae_um": r["model"]["mae_um"], "oracle_mae_um": r["oracle"]["mae_um"],
                             "coverage": r["coverage"]["all"]["coverage"],
                             "coverage_in_domain": r["coverage"]["in_domain"]["coverage"],
                             "out_of_domain_share": r["out_of_domain_share"],
                             "cad_mae_before_after_um": [kp["before"]["mae_um"], kp["after"]["mae_um"]],
                             "cad_p95_before_after_um": [kp["before"]["p95_um"], kp["after"]["p95_um"]]})
                if log:
                    log(f"{tag} {name} {s}: MAE {np.round(rows[-1]['mae_um'], 2)} (oracle "
                        f"{np.round(rows[-1]['oracle_mae_um'], 2)}) µm, coverage {rows[-1]['coverage']:.3f}, OOD "
                        f"{rows[-1]['out_of_domain_share']:.3f}, CAD MAE {kp['before']['mae_um']:.2f} → "
                        f"{kp['after']['mae_um']:.2f} µm")
        result["models"][tag] = {"train_rows": len(tr.X), "rows": rows}
    (out / "seen.json").write_text(json.dumps(result, indent=1))
    return result


def main(argv: list[str] | None = None) -> None:
    """``python -m xmetro_ros.parts_seen OUT [--epochs N] [--train-points N]``."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out")
    ap.add_argument("--epochs", type=int, default=40)
    ap.add_argument("--train-points", type=int, default=400)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    run(a.out, epochs=a.epochs, train_points=a.train_points, seed=a.seed)


if __name__ == "__main__":
    main()
