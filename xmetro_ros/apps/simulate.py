"""`xmetro simulate`: simulate the study campaign and write it to ``DIR/campaign.mcap`` + ``DIR/manifest.json``."""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
from pathlib import Path

from ..scan.artifact_specs import parse_artifact
from ..scan.artifacts import ArtifactSpecError
from ..scan.scanner import ScannerModel
from ..sim.campaign import campaign_manifest, study_campaign
from ..sim.effect import EffectConfigError, UnknownEffectError
from ..sim.effects import EFFECTS

__all__ = ["QUICK_CONFIGS", "register", "run"]

# --quick: three corner/middle configurations (indices into the 27) of the spheres only.
QUICK_CONFIGS = (0, 13, 26)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``xmetro simulate`` to the ``xmetro`` sub-commands."""
    p = subparsers.add_parser(
        "simulate",
        help="simulate the study campaign (spheres x 27 configurations + cylinder) to DIR/campaign.mcap",
        description=__doc__,
    )
    p.add_argument("--out", required=True, type=Path, help="output directory (created; campaign.mcap must not exist)")
    p.add_argument("--seed", type=int, default=0, help="campaign seed (item seeds derive from it)")
    p.add_argument("--quick", action="store_true",
                   help="3 configurations only (of the spheres, or of the --artifact given; a few seconds)")
    p.add_argument(
        "--artifact",
        action="append",
        metavar="SPEC",
        help="artifact instead of the study's (repeatable), e.g. sphere:radius=20, cylinder:radius=15 or "
        "'mesh:path=PART.stl,pose=X;Y;Z;QX;QY;QZ;QW,form_error=UM' (pose in m + quaternion; docs/parts.md)",
    )
    p.add_argument("--effects-off", default="", metavar="A,B", help=f"effects to switch off ({', '.join(EFFECTS)})")
    p.add_argument("--plane", action="store_true", help="add the z = 0 plane to the campaign")
    p.add_argument("--scanner", type=Path, default=None, help="scanner YAML (default: the packaged one)")
    p.add_argument("--exact", action="store_true", help="store float64 points / expected error too (bigger file)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """``xmetro simulate``: simulate the campaign into ``DIR/campaign.mcap`` + manifest; returns the exit code."""
    from tqdm import tqdm

    from ..ros.scan_io import write_scans  # BAG's module; imported here so `xmetro --help` stays light

    try:
        scanner = ScannerModel.load(args.scanner)
        off = [n.strip() for n in args.effects_off.split(",") if n.strip()]
        effects = {n: {"enabled": False} for n in off} or None
        artifacts = [parse_artifact(spec)[0] for spec in args.artifact] if args.artifact else None
        if any(a.kind == "mesh" for a in artifacts or []) and importlib.util.find_spec("open3d") is None:
            raise ArtifactSpecError("scanning a mesh needs open3d (pip install 'xmetro_ros[train]')")
        items = study_campaign(scanner, seed=args.seed, plane=args.plane, effects=effects, artifacts=artifacts)
        if args.quick:
            items = [it for it in items if it.config_index in QUICK_CONFIGS and it.artifact.kind == "sphere"] or [
                it for it in items if it.config_index in QUICK_CONFIGS
            ]
    except (UnknownEffectError, EffectConfigError, ArtifactSpecError, ValueError, FileNotFoundError) as e:
        print(f"xmetro simulate: error: {e}", file=sys.stderr)
        return 2
    out: Path = args.out
    bag = out / "campaign.mcap"
    if bag.exists():
        print(f"xmetro simulate: error: {bag} already exists", file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    manifest = campaign_manifest(
        items, seed=args.seed, effects=effects, extra={"quick": bool(args.quick), "bag": bag.name}
    )
    counts: list[int] = []
    t0 = time.perf_counter()

    def scans():
        for it in tqdm(items, desc="simulate", unit="scan", file=sys.stderr):
            scan = it.simulate()
            counts.append(scan.n_valid)
            yield scan

    write_scans(bag, scans(), manifest=manifest, exact=args.exact)
    manifest["n_points"] = counts
    manifest["seconds"] = round(time.perf_counter() - t0, 2)
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1))
    print(f"wrote {len(items)} scans ({sum(counts)} points) to {bag} in {manifest['seconds']} s")
    return 0
