"""`xmetro demo`: the whole product in one command (``make demo``).

1. start ``xmetro_node`` as a child process (localhost-only DDS: ``ros_env``; a private network namespace when
   run through tools/netns_run), with the shipped default model (or ``--model``);
2. replay ``bags/demo.mcap`` through it (``--fast``: each scan once the previous one is judged) and record the
   node's outputs to ``out/demo/outputs.mcap``;
3. pick the worst region (around the point with the largest predicted deviation of the scan with the largest
   p95 |error|) and ask the node why (``~/explain``, SHAP) and how to rescan it (``~/recommend_settings``);
4. follow the recommendation in the virtual scanner (the demo bag's scans are simulated: their artifact, settings,
   pose and seed are known): re-simulate the region with the current and the recommended set-up and report the
   actual p95 |error| (noise included) before and after, next to the predicted figures (``xmetro_ros.plan.resim``);
5. write ``out/demo/report.html`` (per-scan quality table, deviation maps predicted vs actual, SHAP, the
   recommendation with its re-simulated check) and print a short summary.

Exit status 0 when every step worked, 1 otherwise (the report is still written with what is there).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["DemoResult", "default_demo_bag", "input_scans", "register", "report_scans", "run", "run_demo",
           "scan_summary_line"]

REGION_RADIUS_M = 0.004
EXPLAIN_MAX_POINTS = 200


def default_demo_bag() -> Path:
    """bags/demo.mcap of the checkout (the demo runs from a clone)."""
    from ..scan.resources import repo_root

    root = repo_root()
    if root is None:
        raise FileNotFoundError("xmetro demo needs the repository's bags/demo.mcap: run it from a clone "
                                "(or pass --bag)")
    return root / "bags" / "demo.mcap"


class DemoResult:
    """What the demo did (for the summary and the tests)."""

    def __init__(self) -> None:
        self.replay: Any = None
        self.outputs: list[Any] = []
        self.worst: dict[str, Any] | None = None
        self.explain: dict[str, Any] | None = None
        self.recommend: dict[str, Any] | None = None
        self.resim: dict[str, float] | None = None  # re-simulated actual p95 before / after the recommendation
        self.report: Path | None = None
        self.timings: dict[str, float] = {}
        self.labels: list[str] = []
        self.errors: list[str] = []

    @property
    def ok(self) -> bool:
        return not self.errors


def _worst_region(outputs: list[Any]) -> dict[str, Any] | None:
    """Scan with the largest p95 |error| norm and its (well measured) point with the largest predicted |deviation|."""
    from ..ros.node_outputs import deviation_arrays

    best = None
    for i, o in enumerate(outputs):
        if o.deviations is None:
            continue
        p95 = float(np.linalg.norm(np.asarray(o.quality.p95_abs_error, dtype=float)))
        if best is None or p95 > best[0]:
            best = (p95, i)
    if best is None:
        return None
    o = outputs[best[1]]
    from ..judge import flags as fl

    pts, dev, flags = deviation_arrays(o.deviations)
    n = np.linalg.norm(dev, axis=1)
    ok = np.isfinite(n) & np.isfinite(pts).all(axis=1)
    # A region the scanner actually measured well enough to judge: no grazing, outlier, out-of-domain or unreliable
    # normal flag (over-tolerance is what we look for); all predicted points if there is none.
    bad = np.uint16(fl.FLAG_GRAZING_INCIDENCE | fl.FLAG_GRAZING_VIEW | fl.FLAG_OUTLIER | fl.FLAG_OUT_OF_DOMAIN
                    | fl.FLAG_UNRELIABLE_NORMAL | fl.FLAG_INVALID_POINT)
    if (ok & ((flags & bad) == 0)).any():
        ok &= (flags & bad) == 0
    if not ok.any():
        return None
    j = int(np.flatnonzero(ok)[np.argmax(n[ok])])
    return {"scan": best[1], "stamp_ns": o.stamp_ns, "center_m": pts[j] * 1e-3, "max_dev_mm": float(n[j]),
            "p95_norm_mm": best[0] * 1e3, "settings": o.quality.settings}


def _ask_services(node_name: str, worst: dict[str, Any], timeout: float) -> tuple[dict, dict]:
    """Call ~/explain and ~/recommend_settings for the worst region; return report dicts (or {"error": ...})."""
    from geometry_msgs.msg import Point
    from rclpy.node import Node

    from ..ros.convert import ns_to_stamp
    from ..ros.rclpy_util import NodeSpinner, call_service
    from ..srv import Explain, RecommendSettings

    c = worst["center_m"]
    region = (f"scan #{worst['scan']}: sphere of radius {REGION_RADIUS_M * 1e3:g} mm around "
              f"({c[0] * 1e3:.1f}, {c[1] * 1e3:.1f}, {c[2] * 1e3:.1f}) mm (largest predicted deviation "
              f"{worst['max_dev_mm'] * 1e3:.1f} µm)")
    explain: dict[str, Any]
    recommend: dict[str, Any]
    with NodeSpinner(lambda ctx: Node("xmetro_demo_client", context=ctx)) as sp:
        ex_cli = sp.node.create_client(Explain, f"/{node_name}/explain")
        rc_cli = sp.node.create_client(RecommendSettings, f"/{node_name}/recommend_settings")
        req = Explain.Request()
        req.scan_stamp = ns_to_stamp(worst["stamp_ns"])
        req.region_center = Point(x=float(c[0]), y=float(c[1]), z=float(c[2]))
        req.region_radius = REGION_RADIUS_M
        req.axes = 0
        req.max_points = EXPLAIN_MAX_POINTS
        try:
            r = call_service(ex_cli, req, timeout=timeout)
            if not r.success:
                explain = {"error": r.message}
            else:
                F, A = len(r.feature_names), len(r.axis_names)
                explain = {
                    "region": region, "feature_names": list(r.feature_names),
                    "feature_units": list(r.feature_units), "axis_names": list(r.axis_names),
                    "mean_abs_shap_um": (np.asarray(r.mean_abs_shap, dtype=float).reshape(F, A) * 1e6).tolist(),
                    "base_values_um": [round(v * 1e6, 2) for v in r.base_values],
                    "n_points": len(r.point_indices), "message": r.message, "model_id": r.model_id,
                }
        except Exception as e:  # report it; the demo goes on
            explain = {"error": f"{type(e).__name__}: {e}"}
        rq = RecommendSettings.Request()
        rq.scan_stamp = req.scan_stamp
        rq.region_center = req.region_center
        rq.region_radius = REGION_RADIUS_M
        try:
            r = call_service(rc_cli, rq, timeout=timeout)
            recommend = _recommend_dict(r, region, worst.get("settings"))
        except Exception as e:
            recommend = {"error": f"{type(e).__name__}: {e}"}
    return explain, recommend


def _settings_text(s: Any) -> str:
    return (f"{s.lateral_density / 1e3:g} pt/mm, {s.direction_density / 1e3:g} profiles/mm, "
            f"{s.exposure_time * 1e3:g} ms")


def _quat_deg(q: Any) -> str:
    """A head rotation relative to the current head pose, as a person reads it: the angle about an axis of the head
    frame (X along the laser line, Y the scan direction, Z the laser axis), and the same rotation as Rz·Ry·Rx
    angles (the recommender's own parametrisation, ``scan.geometry.rotation_xyz``)."""
    from ..scan.geometry import quat_to_matrix, xyz_angles

    r = quat_to_matrix([q.x, q.y, q.z, q.w])
    angle = float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0))))
    if angle < 0.05:
        return "keep the current head orientation"
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    n = float(np.linalg.norm(axis))
    if n < 1e-9:  # 180°: the axis is the eigenvector of eigenvalue 1
        w, v = np.linalg.eigh((r + r.T) / 2)
        axis = v[:, int(np.argmax(w))]
    else:
        axis = axis / n
    rx, ry, rz = np.degrees(xyz_angles(r))
    return (f"turn the head {angle:.1f}° about its axis ({axis[0]:.2f}, {axis[1]:.2f}, {axis[2]:.2f}) in the head "
            f"frame (X laser line, Y scan direction, Z laser axis) = tilt {rx:.1f}° about X, {ry:.1f}° about Y, "
            f"turn {rz:.1f}° about Z (applied Z·Y·X) from the current pose")


def target_orientation_text(current: Any, q_rel: Any) -> str:
    """The recommended head orientation as a target in the frame of the current settings (``current``:
    ScannerSettings, its ``head_pose`` in ``header.frame_id``; ``q_rel``: the recommendation, relative to that pose,
    in the head frame): R_target = R_current · R_rel (``HeadPose.rotated``), as a quaternion and as REP 103 roll,
    pitch, yaw (fixed axes X, Y, Z: R = Rz(yaw) Ry(pitch) Rx(roll))."""
    from ..scan.geometry import matrix_to_quat, quat_to_matrix, xyz_angles

    o = current.head_pose.orientation
    r = quat_to_matrix([o.x, o.y, o.z, o.w]) @ quat_to_matrix([q_rel.x, q_rel.y, q_rel.z, q_rel.w])
    q = matrix_to_quat(r)
    roll, pitch, yaw = np.degrees(xyz_angles(r)) + 0.0  # + 0.0: no "-0.0°"
    frame = current.header.frame_id or "(the scan's frame)"
    return (f"in frame '{frame}': roll {roll:.1f}°, pitch {pitch:.1f}°, yaw {yaw:.1f}° (REP 103, fixed X-Y-Z); "
            f"quaternion (x, y, z, w) = ({q[0]:.4f}, {q[1]:.4f}, {q[2]:.4f}, {q[3]:.4f}); the head turns about the "
            "region's centroid")


def _node_tolerance_m() -> float:
    """The demo node's ``tolerance`` (it runs with the parameter's default), metres."""
    from ..ros.params import default_value

    return float(default_value("tolerance"))


def _recommend_dict(r: Any, region: str, current: Any = None) -> dict[str, Any]:
    if not r.success:
        return {"error": r.message}
    um = 1e6

    def f(v: float) -> str:
        # inf: no point of the region is covered (lit, seen, not grazing) with the current settings and pose.
        return f"{v * um:.2f}" if np.isfinite(v) else "n/a (region not covered)"

    rows = [
        ["region", region],
        ["recommended settings", _settings_text(r.recommended_settings)],
        ["current settings (the judged scan)", _settings_text(current) if current is not None else "unknown"],
        ["recommended head orientation (relative)", _quat_deg(r.recommended_orientation)],
        ["target head orientation", target_orientation_text(current, r.recommended_orientation)
         if current is not None else "unknown (no current head pose)"],
        ["mean |error| before → after [µm]", f"{f(r.mean_abs_error_before)} → {f(r.mean_abs_error_after)}"],
        ["p95 |error| before → after [µm] (systematic + random part at each exposure)",
         f"{f(r.p95_abs_error_before)} → {f(r.p95_abs_error_after)}"],
        ["coverage before → after", f"{r.coverage_before:.3f} → {r.coverage_after:.3f}"],
        [f"meets tolerance (p95 after ≤ {_node_tolerance_m() * um:.1f} µm, the node's `tolerance`)",
         "yes" if r.meets_tolerance else "no"],
    ]
    alts = [[i + 1, _settings_text(a.settings), _quat_deg(a.orientation), f(a.mean_abs_error),
             f(a.p95_abs_error), f"{a.coverage:.3f}", f(a.score)]
            for i, a in enumerate(list(r.alternatives)[:5])]
    return {"rows": rows, "alternatives": alts, "message": r.message, "model_id": r.model_id,
            "alternatives_header": ["rank", "settings", "orientation", "mean |e| [µm]", "p95 |e| [µm]",
                                    "coverage", "score [µm]"],
            "p95_before": f(r.p95_abs_error_before), "p95_after": f(r.p95_abs_error_after),
            "settings": _settings_text(r.recommended_settings), "_settings_msg": r.recommended_settings}


#: Re-simulation seeds per set-up in the demo's check of the recommendation.
RESIM_SEEDS = 3


def input_scans(bag: Path) -> dict[int, Any]:
    """The bag's scans by stamp (ns), with their simulation metadata; {} for bags without xmetro metadata."""
    try:
        from ..ros.scan_io import read_scans

        return {s.stamp_ns: s for s in read_scans(bag)}
    except Exception:  # bags without xmetro metadata: no known artifact, no actual errors
        return {}


def _resimulated(inputs: dict[int, Any], worst: dict[str, Any], recommend: dict[str, Any]
                 ) -> dict[str, float] | None:
    """Actual p95 |error| (µm) in the worst region before and after following the recommendation, re-simulated in
    the virtual scanner from the judged scan's ground truth (``inputs``: the bag's scans by stamp); None when the
    scan is not a simulated one."""
    from ..plan.resim import GroundTruth, Region, resimulate
    from ..ros.convert import settings_from_msg

    src = inputs.get(worst["stamp_ns"])
    if src is None or src.artifact is None or "seed" not in src.meta:
        return None
    truth = GroundTruth.from_scan(src)
    region = Region(centre=np.asarray(worst["center_m"], dtype=np.float64) * 1e3, radius_mm=REGION_RADIUS_M * 1e3)
    settings, pose, *_ = settings_from_msg(recommend["_settings_msg"])
    before = resimulate(truth, region, src.settings, src.pose, n_seeds=RESIM_SEEDS)
    after = resimulate(truth, region, settings, pose, n_seeds=RESIM_SEEDS)
    return {"before_um": before.p95_mm * 1e3, "after_um": after.p95_mm * 1e3,
            "spread_um": max(before.p95_spread_mm, after.p95_spread_mm) * 1e3,
            "coverage_after": after.coverage, "seeds": RESIM_SEEDS}


def report_scans(inputs: dict[int, Any], outputs: list[Any]) -> list[Any]:
    """Report rows: quality, processed points, predicted deviations, actual errors where the artifact is known
    (``inputs``: the bag's scans by stamp)."""
    from ..ros.node_outputs import cloud_arrays, deviation_arrays
    from .report_html import ReportScan

    rows = []
    for i, o in enumerate(outputs):
        src = inputs.get(o.stamp_ns)
        label = f"stamp {o.stamp_ns / 1e9:.3f} s"
        if src is not None:
            art = src.artifact.to_dict() if src.artifact is not None else {}
            label = (f"{art.get('kind', 'artifact')} Ø{2 * float(art.get('radius', 0)):g} mm, "
                     f"{src.settings.label()}" if art else src.settings.label())
        rs = ReportScan(index=i, label=label, quality=o.summary_dict(), settings=_settings_text(o.quality.settings))
        if o.deviations is not None:
            pts, dev, _ = deviation_arrays(o.deviations)
            rs.points_mm, rs.predicted_mm = pts, dev
            a = cloud_arrays(o.deviations)
            if {"ux", "uy", "uz"} <= set(a):
                rs.uncertainty_mm = np.stack([a["ux"], a["uy"], a["uz"]], axis=1).astype(np.float64) * 1e3
            if src is not None and src.artifact is not None:
                actual = np.full_like(pts, np.nan)
                ok = np.isfinite(pts).all(axis=1) & np.isfinite(dev).all(axis=1)
                actual[ok] = src.artifact.errors(pts[ok])
                rs.actual_mm = actual
            if src is not None and src.expected_error is not None and o.deviations.height == src.shape[0] \
                    and int(o.deviations.width) * int(o.deviations.height) == int(np.prod(src.shape)):
                rs.systematic_mm = np.asarray(src.expected_error, dtype=np.float64).reshape(-1, 3)
        rows.append(rs)
    return rows


def run_demo(
    out_dir: str | Path = "out/demo",
    bag: str | Path | None = None,
    model_dir: str | Path | None = None,
    timeout: float = 120.0,
    log: Any = print,
) -> DemoResult:
    """Run the demo (see the module docstring); never raises for a failing step: ``DemoResult.errors`` says."""
    from ..ros.dds_env import apply_ros_env
    from ..ros.node_outputs import read_outputs
    from ..ros.rclpy_util import NodeProcess
    from .replay import replay_bag
    from .report_html import write_report

    res = DemoResult()
    t0 = time.monotonic()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    bag = Path(bag) if bag is not None else default_demo_bag()
    if not bag.exists():
        raise FileNotFoundError(f"bag {bag} does not exist")
    record = out_dir / "outputs.mcap"
    record.unlink(missing_ok=True)
    inputs: dict[int, Any] | None = None  # the bag's scans by stamp, read once when needed
    env_vars = apply_ros_env()  # this process (replay, service clients) and the node share the domain
    params: dict[str, Any] = {"scan_history": 10}
    if model_dir is not None:
        params["model_dir"] = str(Path(model_dir).resolve())
    log(f"xmetro demo: ROS_DOMAIN_ID={env_vars['ROS_DOMAIN_ID']}, localhost-only DDS; node log {out_dir / 'node.log'}")
    node = NodeProcess(params=params, domain_id=int(env_vars["ROS_DOMAIN_ID"]))
    try:
        t = time.monotonic()
        node.start(timeout=timeout)
        res.timings["node_start_s"] = time.monotonic() - t
        t = time.monotonic()
        res.replay = replay_bag(bag, fast=True, record=record, discovery_timeout=timeout, answer_timeout=timeout,
                                log=lambda s: log("  " + s))
        res.timings["replay_s"] = time.monotonic() - t
        res.outputs = read_outputs(record)
        res.worst = _worst_region(res.outputs)
        if res.worst is None:
            res.errors.append("no scan was processed: no region to explain")
        else:
            t = time.monotonic()
            res.explain, res.recommend = _ask_services("xmetro_node", res.worst, timeout)
            res.timings["services_s"] = time.monotonic() - t
            for k, v in (("~/explain", res.explain), ("~/recommend_settings", res.recommend)):
                if "error" in v:
                    res.errors.append(f"{k} failed: {v['error']}")
            if "error" not in res.recommend:
                inputs = input_scans(bag)
                res.resim = _resimulated(inputs, res.worst, res.recommend)
                if res.resim is not None:
                    rs = res.resim
                    res.recommend["rows"].append(
                        ["re-simulated actual p95 |error| before → after [µm] (virtual scanner, "
                         f"{rs['seeds']} seeds each; spread {rs['spread_um']:.2f})",
                         f"{rs['before_um']:.2f} → {rs['after_um']:.2f}"])
        if not res.replay.complete:
            res.errors.append(f"{res.replay.scans_sent - res.replay.answered} scans were not judged")
    except Exception as e:  # a failed step is reported (summary, report); the node is stopped in any case
        res.errors.append(f"{type(e).__name__}: {e}")
    finally:
        node.stop()
        (out_dir / "node.log").write_text("\n".join(node.lines) + "\n")
    t = time.monotonic()
    if res.outputs and inputs is None:
        inputs = input_scans(bag)
    scans = report_scans(inputs or {}, res.outputs) if res.outputs else []
    if res.worst is not None and res.worst["scan"] < len(scans):  # circle the region on its scan's maps
        c = res.worst["center_m"]
        scans[res.worst["scan"]].region_mm = (float(c[0]) * 1e3, float(c[1]) * 1e3, REGION_RADIUS_M * 1e3)
    res.labels = [s.label for s in scans]
    summary = _summary_lines(res)
    res.report = write_report(
        out_dir / "report.html", scans, explain=res.explain, recommend=res.recommend, summary_lines=summary,
        meta={"bag": str(bag), "model": res.outputs[0].quality.model_id if res.outputs else "?",
              "outputs": str(record), "generated": time.strftime("%Y-%m-%d %H:%M:%S")},
        tolerance_m=_node_tolerance_m(),
    )
    res.timings["report_s"] = time.monotonic() - t
    res.timings["total_s"] = time.monotonic() - t0
    return res


def scan_summary_line(index: int, label: str, q: dict[str, Any]) -> str:
    """One judged scan as the demo's and `xmetro report`'s summaries print it (``q``: ``OutputSet.summary_dict()``)."""
    vn = ("OK", "WARN", "RESCAN", "ERROR")[q["verdict"]]
    return (f"  #{index} {label}: {vn:<6s} usable {q['usable_fraction']:.2f} of valid points, "
            f"p95 |e| x/y/z = " + "/".join(f"{v * 1e3:.1f}" for v in q["p95_abs_error_mm"]) + " µm"
            + (" (settings defaulted)" if q["settings_defaulted"] else ""))


def _summary_lines(res: DemoResult) -> list[str]:
    lines = []
    if res.replay is not None:
        r = res.replay
        lines.append(f"replayed {r.scans_sent} scans ({r.settings_sent} settings) in {r.wall_s:.1f} s; "
                     f"{r.answered} judged")
        for i, o in enumerate(res.outputs):
            q = o.summary_dict()
            label = res.labels[i] if i < len(res.labels) else f"@{q['stamp_ns'] / 1e9:.0f}s"
            lines.append(scan_summary_line(i, label, q))
    if res.worst is not None:
        c = res.worst["center_m"] * 1e3
        lines.append(f"worst region: scan #{res.worst['scan']} around ({c[0]:.1f}, {c[1]:.1f}, {c[2]:.1f}) mm, "
                     f"max predicted |deviation| {res.worst['max_dev_mm'] * 1e3:.1f} µm")
    if res.explain and "error" not in res.explain:
        ms = np.asarray(res.explain["mean_abs_shap_um"]).sum(axis=1)
        top = np.argsort(-ms)[:3]
        lines.append("explain (SHAP): top features by mean |SHAP| summed over x, y, z: " + ", ".join(
            f"{res.explain['feature_names'][i]} ({ms[i]:.2f} µm)" for i in top)
            + " (definitions: the report's SHAP table)")
    if res.recommend and "error" not in res.recommend:
        rc = res.recommend
        lines.append(f"recommend: {rc['settings']}; predicted p95 |error| in the region {rc['p95_before']} → "
                     f"{rc['p95_after']} µm (systematic + random part at each exposure)")
        if res.resim is not None:
            lines.append(f"re-simulated (virtual scanner, {res.resim['seeds']} seeds): actual p95 |error| "
                         f"{res.resim['before_um']:.2f} → {res.resim['after_um']:.2f} µm")
    lines += [f"ERROR: {e}" for e in res.errors]
    if res.timings:
        lines.append("timings: " + ", ".join(f"{k} {v:.1f}" for k, v in res.timings.items()))
    return lines


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``xmetro demo`` to the ``xmetro`` sub-commands."""
    p = subparsers.add_parser("demo", help="start a node, replay bags/demo.mcap, write out/demo/report.html",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="out/demo", help="output directory (default out/demo)")
    p.add_argument("--bag", default=None, help="bag to replay (default: the repository's bags/demo.mcap)")
    p.add_argument("--model", default=None, help="model directory (default: the shipped default model)")
    p.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for the node / each answer")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """``xmetro demo``: run the demo and print its summary; returns the exit code."""
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    try:
        res = run_demo(args.out, args.bag, args.model, args.timeout)
    except (OSError, ValueError) as e:
        print(f"xmetro demo: error: {e}", file=sys.stderr)
        return 1
    print("\n".join(_summary_lines(res)))
    print(f"report: {res.report}")
    return 0 if res.ok else 1
