"""`xmetro calibrate CAMPAIGN --out DIR`: from a recorded calibration campaign to a model set of THAT scanner.

1. read the campaign file (:mod:`xmetro_ros.campaign_file`: scanner description, certified spheres and ball bars,
   recordings with known or fitted positions);
2. read every recording (our ``xmetro record`` output or any rosbag2 bag, directory or bare .mcap: PointCloud2 +
   ScannerSettings, no simulator metadata needed), assemble one measurement per sphere and scan, and check the
   data before training (:mod:`xmetro_ros.campaign_data`; every error names the scan and the cause);
3. compute the study's features with the campaign's scanner geometry (not the packaged virtual scanner's), train
   with the study's protocol (point and cloud splits, ``--families``), export model sets whose card records the
   scanner (id, serial), the campaign (hash, artifacts and certificates, positions), the data checks and metrics;
4. write ``DIR/report.md`` and ``DIR/report.json``: per settings the VDI/VDE 2634-2 probing form / size and sphere
   spacing figures, the data checks, and the models' accuracy on held-out points and held-out configurations.

Lengths in mm in the reports. Exit code 2 on a campaign error, with its message.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

__all__ = ["calibrate", "register", "run"]


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``xmetro calibrate`` to the ``xmetro`` sub-commands."""
    from ..learn.families import PROFILES

    p = subparsers.add_parser("calibrate", help="train a model of a real scanner from a recorded calibration "
                              "campaign", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("campaign", help="campaign file (YAML, format xmetro-campaign/1; see docs/calibration.md)")
    p.add_argument("--out", required=True, help="output directory (models/, report.md, report.json, metrics)")
    p.add_argument("--profile", choices=sorted(PROFILES), default="quick")
    p.add_argument("--families", default="catboost,pointnet_multi", help="comma-separated model families")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-points", type=int, default=2000, help="points sampled per measurement")
    p.set_defaults(func=run)


def _read(rec: Any, scanner: Any) -> list[Any]:
    from ..ros.scan_io import read_scans

    return read_scans(rec.bag, topic=rec.scan_topic, settings_topic=rec.settings_topic, scanner=scanner)


def calibrate(campaign_path: str | Path, out: str | Path, *, profile: str = "quick",
              families: tuple[str, ...] = ("catboost", "pointnet_multi"), seed: int = 0, max_points: int = 2000,
              log: Any = print) -> dict[str, Any]:
    """Run the whole calibration (module docstring); return the report dict. Raises CampaignError."""
    from .. import vdi2634
    from ..campaign_data import assemble
    from ..campaign_file import load_campaign
    from ..dataset import build_table
    from ..features import STUDY_FEATURES
    from ..learn.study import run_study

    t0 = time.perf_counter()
    out = Path(out)
    camp = load_campaign(campaign_path)
    log(f"campaign {camp.path.name}: scanner {camp.scanner_id} ({camp.scanner_serial or 'no serial'}), "
        f"{len(camp.artifacts)} spheres, {len(camp.ball_bars)} ball bars, {len(camp.recordings)} recordings")
    data = assemble(camp, lambda rec: _read(rec, camp.scanner))
    log(f"{data.checks.n_measurements} measurements from {data.checks.n_scans_read} scans; settings levels "
        f"{data.checks.settings_levels}")
    fitted = any(it.placement.fitted for it in data.scans)
    table = build_table([it.scan for it in data.scans], STUDY_FEATURES, max_points_per_cloud=max_points, seed=seed,
                        scanner=data.scanner)
    manifest = {"source": "calibration campaign", "campaign": camp.card(), "checks": data.checks.to_dict()}
    card_extra = {
        "scanner": {"id": camp.scanner_id, "serial": camp.scanner_serial, "description": camp.scanner.source},
        "campaign": camp.card(), "data_checks": data.checks.to_dict(),
        "positions": "fitted (location errors removed from the targets)" if fitted else "known",
        "trained_by": f"xmetro calibrate {camp.path.name} --profile {profile} --seed {seed}",
    }
    metrics = run_study(table, manifest, profile, seed, out, families=families, log=log, timing=False,
                        card_extra=card_extra)
    probing_rows = [{"recording": it.recording, "scan": it.index, "artifact": it.placement.artifact,
                     "settings": it.scan.settings.label(), "position": "fitted" if it.placement.fitted else "known",
                     **it.figures.to_dict()} for it in data.scans]
    report = {
        "schema": "xmetro-calibration-report/1",
        "campaign": camp.card(),
        "checks": data.checks.to_dict(),
        "positions": card_extra["positions"],
        "vdi2634": {"per_measurement": probing_rows, "spacing": data.spacing,
                    "per_settings": vdi2634.summarize([*probing_rows, *data.spacing])},
        "models": {s: metrics["splits"][s]["models"] for s in metrics["splits"]},
        "model_dirs": {fam: str(out / "models" / fam) for fam in families},
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    (out / "report.json").write_text(json.dumps(report, indent=2, default=float))
    (out / "report.md").write_text(_markdown(report))
    log(f"wrote {out / 'report.md'} and model sets under {out / 'models'} ({report['wall_s']:.0f} s)")
    return report


def _markdown(r: dict[str, Any]) -> str:
    c = r["campaign"]
    lines = [f"# Calibration of scanner {c['scanner']['id']} (serial {c['scanner']['serial'] or '-'})", "",
             f"Campaign `{c['file']}` (sha256 `{c['sha256'][:16]}…`); positions: {r['positions']}.", "",
             "## Certified artifacts", "", "| id | kind | size (mm) | U (mm) | certificate |", "|---|---|---|---|---|"]
    for a in c["artifacts"]:
        lines.append(f"| {a['id']} | sphere | Ø {a['diameter_mm']:.4f} | {a['size_uncertainty_mm']:.4f} | "
                     f"{a['certificate']} |")
    for b in c["ball_bars"]:
        lines.append(f"| {b['id']} | ball bar {'–'.join(b['spheres'])} | L {b['distance_mm']:.4f} | "
                     f"{b['distance_uncertainty_mm']:.4f} | {b['certificate']} |")
    ch = r["checks"]
    lines += ["", "## Data checks", "", f"- {ch['n_measurements']} measurements from {ch['n_scans_read']} scans; "
              f"per artifact {ch['per_artifact']}", f"- settings levels {ch['settings_levels']}"
              + (" (taken from the campaign)" if ch["levels_from_campaign"] else ""),
              f"- median angle estimated vs nominal normals {ch['median_normal_angle_deg']:.1f}°; largest free-fit "
              f"radius deviation {ch['radius_deviation_max_mm'] * 1e3:.1f} µm"]
    lines += [f"- {n}" for n in ch["notes"]]
    lines += ["", "## VDI/VDE 2634-2 figures per settings (largest |value|, µm)", "",
              "| settings | PF | PS | SD | n |", "|---|---|---|---|---|"]
    for s, d in r["vdi2634"]["per_settings"].items():
        def f(k: str, d: dict = d) -> str:
            return f"{d[k]['max_abs'] * 1e3:.1f}" if k in d else "–"
        n = d.get("PF_mm", {}).get("n", 0)
        lines.append(f"| {s} | {f('PF_mm')} | {f('PS_mm')} | {f('SD_mm')} | {n} |")
    lines += ["", "## Models (MAE µm, mean over the test draws; R²)", "",
              "| split | family | X | Y | Z |", "|---|---|---|---|---|"]
    for split, fams in r["models"].items():
        for fam, axes in fams.items():
            cells = [f"{axes[a]['mae']['mean'] * 1e3:.2f} (R² {axes[a]['r2']['mean']:.2f})" for a in ("x", "y", "z")]
            lines.append(f"| {split} | {fam} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    """``xmetro calibrate``: returns the exit code (2 with the reason on a campaign error)."""
    from ..campaign_file import CampaignError

    fams = tuple(f.strip() for f in args.families.split(",") if f.strip())
    try:
        calibrate(args.campaign, args.out, profile=args.profile, families=fams, seed=args.seed,
                  max_points=args.max_points)
    except (CampaignError, ValueError, FileNotFoundError) as e:
        print(f"xmetro calibrate: error: {e}")
        return 2
    return 0
