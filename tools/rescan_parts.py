"""Parts rescanned from the recommender's tilted head poses, judged as the node judges them (the shipped primary and
pose model, routing): ``python tools/rescan_parts.py [POSE_MODEL_DIR]``.

Each of the test parts ``blade``, ``bowl`` and ``step`` (never in a training or calibration campaign) is scanned at
6/3/0.1 and 10/4/0.5 from three head poses of ``pose_grid()`` (tilted 15° or 21°, turned), seed 21, and scored by
``parts.study.evaluate_part`` against the simulator's truth: the model that judged it, the share of points flagged
out of domain, the in-domain coverage of |actual − d| ≤ U per axis and of |after − true form| ≤ u_normal along the
CAD normal. Its table is quoted in docs/parts-generalisation.md ("Rescans from a tilted head").
"""

from __future__ import annotations

import sys

import numpy as np

from xmetro_ros.judge.inference import ModelSet
from xmetro_ros.judge.scan_handler import ScanHandler
from xmetro_ros.parts.study import evaluate_part
from xmetro_ros.scan.resources import pose_model_dir
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim.campaign import pose_grid

PARTS = ("blade", "bowl", "step")
GRID = (0, 1, 14)  # 21° tilted; 15° tilted; 15° tilted and turned
SETTINGS = (ScanSettings(6.0, 3.0, 0.1), ScanSettings(10.0, 4.0, 0.5))


def main(pose_dir: str | None = None) -> None:
    pose = ModelSet.load(pose_dir or pose_model_dir())
    h = ScanHandler(ModelSet.load(), ScannerModel.load(), pose_model=pose)
    grid = pose_grid()
    print(f"pose model {pose.id} ({pose_dir or 'shipped'}); seed 21; coverage of the in-domain points (%)")
    print("| part | head pose (tilt) | setting | judged by | out of domain | x | y | z | along the normal |")
    print("|---|---|---|---|---|---|---|---|---|")
    for part in PARTS:
        for gi in GRID:
            tilt = float(np.degrees(np.arccos(np.clip(grid[gi][2, 2], -1.0, 1.0))))
            for st in SETTINGS:
                r = evaluate_part(part, h, st, seed=21, register=False, head_rotation=grid[gi])
                cov = r["coverage"]["in_domain"]["coverage_xyz"] or [float("nan")] * 3
                who = "pose model" if r["judged_by"] == pose.id else "primary"
                ood = 100 * r["out_of_domain_share"]
                print(f"| {part} | {gi} ({tilt:.0f}°) | {st.label()} | {who} | {ood:.1f} % | "
                      + " | ".join(f"{100 * c:.1f}" for c in cov)
                      + f" | {100 * r['cad']['known_pose']['normal_coverage_in_domain']:.1f} |", flush=True)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else None)
