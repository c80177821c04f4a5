"""The training campaign's two sphere sizes (Ø 55 and 35 mm, new scans), judged with the shipped card and with the
card in DIR, scored against the simulator's truth as ``tools/normal_projection.py`` scores its scans: in domain,
each axis' coverage of |actual − d| ≤ U and the coverage along the true normal, at the parts study's three settings.

    python tools/sphere_coverage.py DIR [OUT]   # OUT: docs/results/parts/along_normal/spheres.json

DIR is a card with the along-normal block (``xmetro export-default --from-packaged --add-surfaces --along-normal
--out DIR``; docs/along-normal.md). About 1 minute here.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from normal_projection import _in, _scores, judge

from xmetro_ros.judge.inference import ModelSet
from xmetro_ros.judge.scan_handler import ScanHandler
from xmetro_ros.parts.study import DEFAULT_SETTINGS
from xmetro_ros.scan.artifacts import Sphere
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings

ROOT = Path(__file__).resolve().parents[1]
RADII_MM = (27.5, 17.5)


def main(model_dir: str, out: str | None = None) -> None:
    sc = ScannerModel.load()
    result: dict = {"seed": 0, "cards": {}}
    for label, ms in (("shipped", ModelSet.load()), ("block", ModelSet.load(model_dir))):
        h = ScanHandler(ms, sc)
        rows = []
        for radius in RADII_MM:
            for st in DEFAULT_SETTINGS:
                r = judge(h, Sphere(radius, (0.0, 0.0, 0.0)), ScanSettings(*st))
                s = _scores(r, r["d"], r["u"])
                cov = [*s["coverage_xyz"], s["coverage_normal"]]
                rows.append({"radius_mm": radius, "settings": list(st), "coverage_xyz": s["coverage_xyz"],
                             "coverage_normal": s["coverage_normal"], "in_bounds": _in(cov)})
                print(label, f"R{radius:g}", "/".join(f"{v:g}" for v in st),
                      " / ".join(f"{100 * c:.1f}" for c in cov), flush=True)
        result["cards"][label] = {"model": ms.id, "along_normal": ms.along_normal is not None, "rows": rows}
    path = Path(out) if out else ROOT / "docs" / "results" / "parts" / "along_normal" / "spheres.json"
    path.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2] if len(sys.argv) > 2 else None)
