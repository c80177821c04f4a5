"""`xmetro parts`: the test parts generated in code, and the generalisation study on them (docs/parts.md,
docs/parts-generalisation.md).

    xmetro parts write DIR [--form-um 40] [--format stl|ply]   CAD (and manufactured, with --form-um) meshes
    xmetro parts scan PART OUT.mcap [--form-um 40] [--pose P]   a simulated scan of the manufactured part in a bag,
                                                                 its CAD as OUT_cad.stl, the CAD pose printed;
                                                                 PART: a generated part or a mesh file (mm)
    xmetro parts study OUT [--model DIR] [--parts blade,bowl]   simulate, judge, score: OUT/<part>.json, .png,
                                                                 summary.json

Both need the ``[train]`` extra (open3d for the mesh queries and ICP, matplotlib for the maps).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

__all__ = ["register", "run_scan", "run_study_cmd", "run_write"]


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``xmetro parts`` to the ``xmetro`` sub-commands."""
    p = subparsers.add_parser("parts", help="test parts from code: write their meshes, run the generalisation study",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="parts_command", metavar="ACTION", required=True)
    w = sub.add_parser("write", help="write the parts' CAD meshes (and manufactured ones with --form-um)")
    w.add_argument("dir", help="output directory of the meshes")
    w.add_argument("--form-um", type=float, default=0.0, help="also write the manufactured parts with this form "
                                                               "error amplitude (µm)")
    w.add_argument("--format", choices=("stl", "ply"), default="stl", help="mesh file format (default stl)")
    w.add_argument("--step-mm", type=float, default=0.3, help="grid step of the surfaces (mm)")
    w.set_defaults(func=run_write)
    sc = sub.add_parser("scan", help="simulate a scan of a manufactured part into a bag (+ its CAD as STL)")
    sc.add_argument("part", help="a generated part (blade, bowl, step, fillet) or a mesh file (.stl/.ply/.obj, mm)")
    sc.add_argument("out", metavar="OUT.mcap", help="the bag to write")
    sc.add_argument("--form-um", type=float, default=40.0, help="form error amplitude of the manufactured part (µm)")
    sc.add_argument("--pose", default=None, metavar="X,Y,Z,QX,QY,QZ,QW",
                    help="part → scan frame, m + quaternion (default: the study's for a generated part, else identity)")
    sc.add_argument("--settings", default="10,4,0.5", help="lateral density /mm, direction density /mm, exposure ms")
    sc.add_argument("--seed", type=int, default=0, help="seed of the simulated scan (default 0)")
    sc.set_defaults(func=run_scan)
    s = sub.add_parser("study", help="generalisation of a model set to the mesh parts (docs/parts-generalisation.md)")
    s.add_argument("out", help="output directory (results, plots)")
    s.add_argument("--model", default=None, metavar="DIR", help="model set (default: the shipped one)")
    s.add_argument("--parts", default=None, help="comma-separated part names (default: all)")
    s.add_argument("--seed", type=int, default=0, help="seed of the simulated scans (default 0)")
    s.add_argument("--no-plots", action="store_true", help="write the results without the PNG plots")
    s.set_defaults(func=run_study_cmd)


def run_write(args: argparse.Namespace) -> int:
    """``xmetro parts write``."""
    from ..scan.generated_parts import PARTS, make_part
    from ..scan.mesh import write_ply, write_stl

    out = Path(args.dir)
    out.mkdir(parents=True, exist_ok=True)
    writer = write_stl if args.format == "stl" else write_ply
    for name in PARTS:
        for form in ([0.0, args.form_um] if args.form_um else [0.0]):
            m = make_part(name, form_um=form, step_mm=args.step_mm)
            path = writer(out / f"{name}{'' if not form else f'_form{form:g}um'}.{args.format}", m.vertices,
                          m.triangles)
            print(f"{path}: {len(m.triangles)} triangles")
    return 0


def _is_mesh_path(part: str) -> bool:
    return Path(part).suffix.lower() in (".stl", ".ply", ".obj") or Path(part).exists()


def run_scan(args: argparse.Namespace) -> int:
    """``xmetro parts scan``: a generated part as the study presents it (``parts_study.PRESENTATION``) or a mesh
    file (identity pose) — or placed by ``--pose`` (m + quaternion, ``scan.part_pose``) —, manufactured with the
    form error ``--form-um``, one scan in a bag (``ros.scan_io``; the scan's artifact record keeps the form
    error's truth), the CAD next to it (a generated part's as OUT_cad.stl; a mesh file is its own CAD); prints the
    ``--cad-pose`` for ``xmetro predict`` (7 numbers, m + quaternion)."""
    from ..parts.study import PRESENTATION
    from ..ros.scan_io import write_scans
    from ..scan.artifact_specs import load_part_mesh
    from ..scan.artifacts import ArtifactSpecError
    from ..scan.generated_parts import PARTS, make_part
    from ..scan.mesh import write_stl
    from ..scan.part_pose import PoseError, format_pose7, parse_pose7
    from ..scan.scanner import ScannerModel, ScanSettings
    from ..sim import simulate_scan

    is_mesh = args.part not in PARTS and _is_mesh_path(args.part)
    if args.part not in PARTS and not is_mesh:
        print(f"xmetro parts scan: unknown part {args.part!r} (known: {', '.join(PARTS)}; or a mesh file "
              ".stl, .ply, .obj)", file=sys.stderr)
        return 2
    try:
        pose = PRESENTATION if args.pose is None and not is_mesh else parse_pose7(args.pose, what="--pose", sep=",")
        st = ScanSettings(*(float(x) for x in args.settings.split(",")))
        if is_mesh:
            man = load_part_mesh(args.part, pose=pose, form_um=args.form_um)
        else:
            man = make_part(args.part, form_um=args.form_um).transformed(pose)
        scan = simulate_scan(man, st, scanner=ScannerModel.load(), seed=args.seed)
    except (PoseError, ArtifactSpecError, ValueError, TypeError) as e:
        print(f"xmetro parts scan: error: {e}", file=sys.stderr)
        return 2
    out = Path(args.out)
    write_scans(out, [scan])
    if is_mesh:
        cad_path = str(args.part)
    else:
        cad = make_part(args.part)
        cad_path = str(write_stl(out.with_name(out.stem + "_cad.stl"), cad.vertices, cad.triangles))
    print(f"{out}: 1 scan, {scan.n_valid} points; CAD {cad_path}; --cad-pose \"{format_pose7(pose)}\"")
    return 0


def run_study_cmd(args: argparse.Namespace) -> int:
    """``xmetro parts study``."""
    from ..parts.study import DEFAULT_PARTS, run_study
    from ..scan.generated_parts import PARTS

    parts = tuple(args.parts.split(",")) if args.parts else DEFAULT_PARTS
    unknown = [p for p in parts if p not in PARTS]
    if unknown:
        print(f"xmetro parts study: unknown part(s) {unknown} (known: {', '.join(PARTS)})", file=sys.stderr)
        return 2
    summary = run_study(args.out, model_dir=args.model, parts=parts, seed=args.seed, plots=not args.no_plots)
    print(json.dumps({"model": summary["model"], "out": str(args.out)}))
    return 0
