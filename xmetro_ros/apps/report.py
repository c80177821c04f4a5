"""`xmetro report BAG --out REPORT.html`: the demo's HTML report for any judged bag — the node's outputs recorded
live (``xmetro record`` / ``xmetro replay --record``) or written by ``xmetro predict``.

Per scan: the quality table (verdict, valid / usable / flagged, predicted p95 |d| and U per axis, decisions), a
predicted-deviation map and a U map; where the bag also holds the input scans with their simulation metadata
(our simulated bags), the actual and systematic errors beside them. ``~/explain`` and ``~/recommend_settings``
need a live node: `xmetro demo --bag BAG` asks them. Exit 2 when the bag holds no judged scan (with what to run).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["register", "run", "write_bag_report"]


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``xmetro report``."""
    p = subparsers.add_parser("report", help="write the HTML report of a judged bag (node or predict output)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bag", help="a judged bag (.mcap or rosbag2 directory) holding the node's ~/quality outputs")
    p.add_argument("--out", required=True, metavar="REPORT.html", help="the HTML file to write")
    p.add_argument("--node-name", default="xmetro_node", help="the node whose outputs to read (default xmetro_node)")
    p.add_argument("--tolerance", type=float, default=None, metavar="METRES",
                   help="the judging node's `tolerance` parameter, stated beside the decisions (a bag does not record "
                        "it; default: the node's)")
    p.set_defaults(func=run)


def write_bag_report(bag: str | Path, out: str | Path, node_name: str = "xmetro_node",
                     tolerance_m: float | None = None) -> Path:
    """Write the report of ``bag``'s judged scans to ``out``; ValueError when it holds none. ``tolerance_m``: the
    judging node's ``tolerance`` (None: the parameter's default), stated with the decisions."""
    from ..ros.node_outputs import read_outputs
    from ..ros.params import default_value
    from .demo import input_scans, report_scans, scan_summary_line
    from .report_html import write_report

    if tolerance_m is not None and not tolerance_m > 0:
        raise ValueError(f"--tolerance must be a positive length in metres, got {tolerance_m:g}")
    outputs = read_outputs(bag, node_name=node_name)
    if not outputs:
        raise ValueError(f"{bag} holds no /{node_name.strip('/')}/quality message: judge it first "
                         f"(xmetro predict {bag} --out JUDGED.mcap)")
    scans = report_scans(input_scans(Path(bag)), outputs)
    models = sorted({str(o.quality.model_id) for o in outputs} - {""})
    lines = [f"{len(outputs)} judged scans in {bag}"]
    lines += [scan_summary_line(s.index, s.label, s.quality) + (f" — {s.quality['message']}"
                                                                if s.quality["message"] else "") for s in scans]
    return write_report(out, scans, summary_lines=lines,
                        meta={"bag": str(bag), "model set(s)": ", ".join(models) or "-"},
                        title=f"xmetro report: {Path(bag).name}",
                        services_note=f"not in a recorded bag: `xmetro demo --bag {bag}` asks a live node",
                        tolerance_m=float(default_value("tolerance")) if tolerance_m is None else tolerance_m,
                        tolerance_note=("the node's default <code>tolerance</code>: a bag does not record the node's "
                                        "parameters, <code>xmetro report --tolerance</code> states another"
                                        if tolerance_m is None else "<code>xmetro report --tolerance</code>"))


def run(args: argparse.Namespace) -> int:
    """``xmetro report``: exit 0 with the report written, 2 with the reason on stderr."""
    from ..bag.reader import BagFormatError

    try:
        path = write_bag_report(args.bag, args.out, node_name=args.node_name, tolerance_m=args.tolerance)
    except (ValueError, BagFormatError, OSError) as e:
        print(f"xmetro report: error: {e}", file=sys.stderr)
        return 2
    print(f"report: {path}")
    return 0
