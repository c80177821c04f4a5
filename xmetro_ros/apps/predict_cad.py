"""`xmetro predict BAG --out OUT.mcap --cad PART.stl`: each judged scan's deviation map against the part's CAD,
before and after the model's compensation, with U along the normal (``xmetro_ros.parts.cad_judge``).

The node's ``~/deviations`` cloud of each scan (x, y, z as received, predicted deviation dx, dy, dz = measured −
nominal, U ux, uy, uz, flags; metres) is read back, converted to mm (the deviations turned back into the model's
target by ``ros.node_outputs.deviation_arrays``, what ``cad_deviation`` takes) and compared with the CAD placed by
``--cad-pose`` (part → scan frame: x, y, z in metres and the quaternion qx, qy, qz, qw, the node's ``cad_pose``
parameter, ``scan.part_pose``; default identity; the 12-number millimetre matrix of xmetro ≤ 0.5 is refused) or
registered on the compensated scan (``--cad-register``: point-to-plane ICP from that pose, its fit and uncertainty
reported). Needs open3d (``[train]`` extra) for the mesh queries. Writes ``--cad-report`` (JSON; default OUT.cad.json).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["cad_reports", "parse_pose", "summary_lines"]


def parse_pose(text: str | None) -> np.ndarray:
    """The (4, 4) mm pose of ``--cad-pose``: 7 numbers x, y, z (m), qx, qy, qz, qw separated by spaces or commas;
    None/empty → identity. Raises ``PoseError`` (a ValueError), e.g. for the old 12-number form, with the 7
    numbers to use instead."""
    from ..scan.part_pose import parse_pose7

    return parse_pose7(text, what="--cad-pose")


def cad_reports(outputs: list[Any], cad_path: str | Path, *, pose: np.ndarray | None = None,
                register: bool = False, report: str | Path | None = None) -> list[dict[str, Any]]:
    """The CAD deviation summary of each output set with a ``~/deviations`` cloud (``OutputSet`` of
    ``predict_bag``); written to ``report`` (JSON) when given."""
    from ..parts.cad_judge import cad_deviation
    from ..ros.cloud import read_points_numpy
    from ..ros.node_outputs import deviation_arrays
    from ..scan.mesh import MeshArtifact

    cad = MeshArtifact.from_file(cad_path)
    rows: list[dict[str, Any]] = []
    for k, o in enumerate(outputs):
        if o.deviations is None:
            rows.append({"scan": k, "error": "no deviations (scan in ERROR or not kept)"})
            continue
        # points and the model's target nominal − measured (the published d turned back), mm; U in mm
        pts, target, flags = deviation_arrays(o.deviations)
        u = read_points_numpy(o.deviations, ["ux", "uy", "uz"]).astype(np.float64) * 1e3
        dev = cad_deviation(cad, pts, target, u, flags=flags, pose=pose, register=register)
        rows.append({"scan": k, "stamp_ns": int(o.stamp_ns), **dev.summary()})
    if report is not None:
        Path(report).write_text(json.dumps({"cad": str(cad_path), "scans": rows}, indent=1))
    return rows


def summary_lines(rows: list[dict[str, Any]]) -> list[str]:
    """One line per scan: mean / p95 |measured − CAD| before → after compensation, mean U along the normal."""
    out = []
    for r in rows:
        if "error" in r:
            out.append(f"cad #{r['scan']}: {r['error']}")
            continue
        b, a, u = r["before"], r["after"], r["u_normal"]
        reg = r.get("registration")
        out.append(f"cad #{r['scan']}: {r['points']} points, |measured − CAD| mean {b['mean_abs']:.2f} → "
                   f"{a['mean_abs']:.2f} µm, p95 {b['p95_abs']:.2f} → {a['p95_abs']:.2f} µm (compensated), mean U "
                   f"along the normal {u['mean']:.2f} µm"
                   + (f"; registered: RMSE {reg['rmse_mm'] * 1e3:.2f} µm, fitness {reg['fitness']:.3f}" if reg else ""))
    return out
