"""U's coverage per 10° incidence bin × exposure level (as ``test/test_uncertainty_conditions.py`` measures it for the
shipped card), for the shipped card and for the card in DIR: held-out spheres Ø 40 and 50 mm and a cylinder r 15 mm
at all 27 study settings (campaign seed 4242), judged by ``ScanHandler.process``, scored against the simulator's
truth (nominal − measured of each published point, noise included).

    python tools/condition_coverage.py DIR [OUT]   # OUT: docs/results/parts/along_normal/conditions.json

DIR: e.g. a card with the along-normal block (docs/along-normal.md). About 5 minutes here.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from xmetro_ros.judge.inference import ModelSet
from xmetro_ros.judge.scan_handler import ScanHandler
from xmetro_ros.scan.artifacts import Cylinder, Sphere
from xmetro_ros.scan.scanner import ScannerModel
from xmetro_ros.scan.targets import point_errors
from xmetro_ros.sim.campaign import study_campaign

ROOT = Path(__file__).resolve().parents[1]
EDGES = np.arange(0.0, 91.0, 10.0)
MIN_CELL_POINTS = 2000  # the test's: fewer points give a binomial spread of more than ±1 %
FLOOR = 0.93


def cells(handler: ScanHandler, items: list) -> list[dict]:
    """Coverage per axis of every incidence bin × exposure cell with at least MIN_CELL_POINTS points."""
    inc, exp, hit = [], [], []
    for it in items:
        scan = it.simulate()
        r = handler.process(scan)
        idx = np.asarray(r.prepared.index)
        d, U = r.deviations[idx], r.uncertainty[idx]
        actual = point_errors(r.prepared.points, scan.artifact)
        pub = np.isfinite(d).all(1) & np.isfinite(U).all(1) & np.isfinite(actual).all(1)
        n = np.asarray(r.prepared.normals, np.float64)[pub]
        L = np.asarray(r.prepared.geometry.L, np.float64)[pub]
        inc.append(np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n, L), -1.0, 1.0))))
        exp.append(np.full(int(pub.sum()), scan.settings.exposure_ms))
        hit.append(np.abs(actual[pub] - d[pub]) <= U[pub])
    a_inc, a_exp, a_hit = np.concatenate(inc), np.concatenate(exp), np.concatenate(hit)
    k = np.clip(np.digitize(a_inc, EDGES) - 1, 0, len(EDGES) - 2)
    out = []
    for e in np.unique(a_exp):
        for b in range(len(EDGES) - 1):
            m = (k == b) & (a_exp == e)
            if m.sum() >= MIN_CELL_POINTS:
                out.append({"incidence_deg": [float(EDGES[b]), float(EDGES[b + 1])], "exposure_ms": float(e),
                            "points": int(m.sum()), "coverage_xyz": [float(c) for c in a_hit[m].mean(0)]})
    return out


def main(model_dir: str, out: str | None = None) -> None:
    sc = ScannerModel.load()
    items = study_campaign(sc, seed=4242, artifacts=[Sphere(20.0), Sphere(25.0), Cylinder(15.0)])
    result: dict = {"seed": 4242, "floor": FLOOR, "cards": {}}
    for label, ms in (("shipped", ModelSet.load()), ("given", ModelSet.load(model_dir))):
        cs = cells(ScanHandler(ms, sc), items)
        below = [c for c in cs if min(c["coverage_xyz"]) < FLOOR]
        result["cards"][label] = {"model": ms.id, "along_normal": ms.along_normal is not None, "cells": cs,
                                  "cells_below_floor": len(below)}
        print(f"{label}: {len(below)} of {len(cs)} cells below {FLOOR:g}", flush=True)
        for c in cs:
            print(f"  {c['incidence_deg'][0]:3.0f}-{c['incidence_deg'][1]:.0f} deg, {c['exposure_ms']:g} ms: "
                  + " ".join(f"{100 * v:5.1f}" for v in c["coverage_xyz"]), flush=True)
    path = Path(out) if out else ROOT / "docs" / "results" / "parts" / "along_normal" / "conditions.json"
    path.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2] if len(sys.argv) > 2 else None)
