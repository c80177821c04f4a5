"""`xmetro calibrate CAMPAIGN --out DIR`: from a recorded calibration campaign to a model set of THAT scanner.

1. read the campaign file (:mod:`xmetro_ros.calibrate.campaign_file`: scanner description, certified spheres and ball
bars,
   recordings with known or fitted positions);
2. read every recording (our ``xmetro record`` output or any rosbag2 bag, directory or bare .mcap: PointCloud2 +
   ScannerSettings, no simulator metadata needed), assemble one measurement per sphere and scan, and check the
   data before training (:mod:`xmetro_ros.calibrate.campaign_data`; every error names the scan and the cause);
3. compute the study's features with the campaign's scanner geometry (not the packaged virtual scanner's), train
   with the study's protocol (point and cloud splits, ``--families``), export model sets whose card records the
   scanner (id, serial), the campaign (hash, artifacts and certificates, positions), the data checks and metrics;
4. give every model set an uncertainty calibration (:mod:`xmetro_ros.learn.uncertainty`): whole SCANS are held out
   of training BY SCAN (every sphere of a held-out scan goes with it; seeded permutation of the scans):
   ``CALIBRATION_FRACTION`` of them calibrate the split-conformal multipliers, a further ``COVERAGE_FRACTION``
   judge the 95 % intervals (coverage per axis); the rest trains. The card also gets the multivariate domain of
   the training rows (``domain_mv``);
5. write ``DIR/report.json``, ``DIR/report.md`` and the self-contained ``DIR/report.html``
   (:mod:`xmetro_ros.apps.calibrate_report`): per settings the VDI/VDE 2634-2 probing form / size and sphere
   spacing figures, the data checks, the models' accuracy on held-out points and held-out configurations, the
   interval coverage on the held-out scans, and deviation maps (predicted vs actual error along the sphere's
   normal) of held-out scans (``DIR/deviation_maps/*.png``, embedded in the HTML).

``--prior MODEL_DIR`` (or ``default``, the packaged model set): the ``pointnet_multi`` network starts from that
model set's network (weights and normalisation, rebuilt from its ONNX: :mod:`xmetro_ros.learn.prior`) and is
fine-tuned on the campaign's scans; a prior of other features or another layout than ``--profile``'s is refused
before any data is read. The card's ``prior`` records it.

A campaign of single profiles (``format: xmetro-profile-campaign/1``: a profilometer known only from its data)
goes to :mod:`xmetro_ros.apps.calibrate_profiles` (``--iterations``; docs/real-data.md).

Lengths in mm in the reports. Exit code 2 on a campaign error, with its message.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["CALIBRATION_FRACTION", "COVERAGE_FRACTION", "DEFAULT_FAMILIES", "calibrate", "register", "run",
           "split_scans"]

DEFAULT_FAMILIES = ("pointnet_multi",)  # the node's default family: the one with a spread head (σ̂ per point)
CALIBRATION_FRACTION = 0.25  # of the scans: conformal calibration clouds (never trained on)
COVERAGE_FRACTION = 0.25  # of the scans: judge the calibrated intervals (never trained on nor calibrated with)
MIN_HOLDOUT_SCANS = 2  # per held-out part; below 4 + 2 × this scans in all, no uncertainty calibration


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``xmetro calibrate`` to the ``xmetro`` sub-commands."""
    from ..learn.families import PROFILES

    p = subparsers.add_parser("calibrate", help="train a model of a real scanner from a recorded calibration "
                              "campaign", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("campaign", help="campaign file (YAML, format xmetro-campaign/1; see docs/calibration.md)")
    p.add_argument("--out", required=True, help="output directory (models/, report.md, report.json, metrics)")
    p.add_argument("--profile", choices=sorted(PROFILES), default="quick",
                   help="run profile of the training (quick: minutes; full: the study's protocol)")
    p.add_argument("--families", default=",".join(DEFAULT_FAMILIES),
                   help="comma-separated model families (catboost gets a constant σ̂)")
    p.add_argument("--seed", type=int, default=0, help="seed of the scan split and the fits (default 0)")
    p.add_argument("--max-points", type=int, default=2000, help="points sampled per measurement")
    p.add_argument("--prior", default=None, metavar="MODEL_DIR|default",
                   help="fine-tune the pointnet_multi network of this model set ('default': the packaged one) on the "
                   "campaign; its layout must be --profile's")
    p.add_argument("--iterations", type=int, default=1000,
                   help="profile campaigns (format xmetro-profile-campaign/1) only: CatBoost iterations of d")
    p.add_argument("--no-uncertainty", action="store_true",
                   help="train on every scan; no conformal calibration nor coverage (the card has no 'uncertainty')")
    p.set_defaults(func=run)


def _read(rec: Any, scanner: Any) -> list[Any]:
    from ..ros.scan_io import read_scans

    return read_scans(rec.bag, topic=rec.scan_topic, settings_topic=rec.settings_topic, scanner=scanner)


def split_scans(items: list[Any], seed: int, uncertainty: bool = True) -> dict[str, list[int]]:
    """Indices into ``items`` (CampaignScan) of the train / calibration / coverage parts, split BY SCAN: the
    measurements of one scan (every sphere it shows) share a part. Seeded permutation of the scans; each held-out
    part gets round(fraction × n_scans), at least MIN_HOLDOUT_SCANS; too few scans (or ``uncertainty`` False):
    every measurement trains."""
    keys = sorted({(it.recording, it.index) for it in items})
    n = len(keys)
    n_cal = max(MIN_HOLDOUT_SCANS, round(CALIBRATION_FRACTION * n))
    n_cov = max(MIN_HOLDOUT_SCANS, round(COVERAGE_FRACTION * n))
    if not uncertainty or n - n_cal - n_cov < 4:
        return {"train": list(range(len(items))), "calibration": [], "coverage": []}
    perm = [keys[i] for i in np.random.default_rng(seed).permutation(n)]
    part = {k: "calibration" for k in perm[:n_cal]} | {k: "coverage" for k in perm[n_cal:n_cal + n_cov]}
    out: dict[str, list[int]] = {"train": [], "calibration": [], "coverage": []}
    for i, it in enumerate(items):
        out[part.get((it.recording, it.index), "train")].append(i)
    return out


def _uncertainty(model_dirs: dict[str, Path], train: Any, cal: Any, cov: Any, cal_labels: list[str],
                 log: Any) -> dict[str, Any]:
    """Conformal calibration of each model set on the calibration table, multivariate domain of the training rows,
    interval metrics on the coverage table (per family: the card block and per axis coverage / mean U in mm)."""
    from ..judge.inference import ModelSet, update_card
    from ..learn.uncertainty import calibrate as conformal
    from ..learn.uncertainty import fit_domain, interval_metrics, predict_clouds

    out: dict[str, Any] = {}
    domain = fit_domain(train.X)
    for fam, d in model_dirs.items():
        update_card(d, domain_mv=domain)
        # Per condition, without the envelope over neighbouring incidence bins: a campaign's few thousand points
        # per axis make each condition's multiplier noisy, and the maximum over noisy neighbours widened U by ~2 %
        # (coverage 96.5-97.3 % on new recordings of the test's scanner instead of 94.5-95.7 %).
        block = conformal(d, cal.X, cal.y, cal.cloud_id, cloud_labels=cal_labels, envelope=0)
        pr = predict_clouds(ModelSet.load(d), cov.X, cov.cloud_id)
        m = interval_metrics(pr["errors"], pr["U"], cov.y)  # recordings carry no simulator truth (oracle std)
        out[fam] = {"multiplier": block["multiplier"], "calibration_coverage": block["achieved_coverage_calibration"],
                    "coverage": {ax: {k: v for k, v in m[ax].items() if k != "bins"} for ax in m},
                    "n_coverage_points": len(cov.X)}
        log(f"{fam}: multipliers {[round(k, 2) for k in block['multiplier']]}, coverage on held-out scans "
            + ", ".join(f"{ax} {m[ax].get('coverage', float('nan')):.3f}" for ax in m))
    return out


def calibrate(campaign_path: str | Path, out: str | Path, *, profile: str = "quick",
              families: tuple[str, ...] = DEFAULT_FAMILIES, seed: int = 0, max_points: int = 2000,
              uncertainty: bool = True, prior: str | Path | None = None, log: Any = print) -> dict[str, Any]:
    """Run the whole calibration (module docstring); return the report dict. Raises CampaignError, or PriorError
    (a ValueError) for a ``prior`` that cannot warm-start this calibration's network."""
    from ..calibrate import vdi2634
    from ..calibrate.campaign_data import assemble
    from ..calibrate.campaign_file import load_campaign
    from ..calibrate.dataset import build_table
    from ..judge.features import STUDY_FEATURES
    from ..learn.families import get_profile
    from ..learn.prior import PRIOR_FAMILY, PriorError, check_prior, load_prior
    from ..learn.study import run_study
    from ..learn.train import _pointnet_config
    from .calibrate_report import deviation_maps, markdown, write_html

    t0 = time.perf_counter()
    out = Path(out)
    warm = None
    if prior is not None:  # checked before any recording is read: a wrong prior fails in a second
        if PRIOR_FAMILY not in families:
            raise PriorError(f"--prior warm-starts the {PRIOR_FAMILY} network; --families {','.join(families)} has "
                             "none")
        warm = load_prior(prior)
        check_prior(warm, list(STUDY_FEATURES), _pointnet_config(PRIOR_FAMILY, get_profile(profile), 1), profile)
        log(f"prior {warm.card.get('id')} ({warm.dir}, scanner {warm.to_dict()['scanner']}): {PRIOR_FAMILY} "
            "fine-tuned from it")
    camp = load_campaign(campaign_path)
    log(f"campaign {camp.path.name}: scanner {camp.scanner_id} ({camp.scanner_serial or 'no serial'}), "
        f"{len(camp.artifacts)} spheres, {len(camp.ball_bars)} ball bars, {len(camp.recordings)} recordings")
    data = assemble(camp, lambda rec: _read(rec, camp.scanner))
    log(f"{data.checks.n_measurements} measurements from {data.checks.n_scans_read} scans; settings levels "
        f"{data.checks.settings_levels}")
    fitted = any(it.placement.fitted for it in data.scans)
    parts = split_scans(data.scans, seed, uncertainty)

    def table_of(part: str) -> Any:
        return build_table([data.scans[i].scan for i in parts[part]], STUDY_FEATURES, max_points_per_cloud=max_points,
                           seed=seed, scanner=data.scanner)

    def label(i: int) -> str:
        it = data.scans[i]
        return f"recording {it.recording} scan {it.index} {it.placement.artifact}"

    split_doc = {k: [label(i) for i in v] for k, v in parts.items() if k != "train"}
    if uncertainty and not parts["calibration"]:
        log(f"too few scans ({data.checks.n_scans_read}) to hold out calibration and coverage scans: no uncertainty "
            "calibration")
    table = table_of("train")
    manifest = {"source": "calibration campaign", "campaign": camp.card(), "checks": data.checks.to_dict()}
    card_extra = {
        "scanner": {"id": camp.scanner_id, "serial": camp.scanner_serial, "description": camp.scanner.source},
        "campaign": camp.card(), "data_checks": data.checks.to_dict(),
        "positions": "fitted (location errors removed from the targets)" if fitted else "known",
        "trained_by": f"xmetro calibrate {camp.path.name} --profile {profile} --seed {seed}"
                      + (f" --prior {prior}" if warm is not None else ""),
        "held_out_scans": split_doc,
    }
    if warm is not None:
        card_extra["prior"] = warm.to_dict()
    metrics = run_study(table, manifest, profile, seed, out, families=families, log=log, timing=False,
                        card_extra=card_extra, warm_start=None if warm is None else {PRIOR_FAMILY: warm.module})
    model_dirs = {fam: out / "models" / fam for fam in families}
    unc = (_uncertainty(model_dirs, table, table_of("calibration"), table_of("coverage"),
                        split_doc["calibration"], log) if parts["calibration"] else {})
    probing_rows = [{"recording": it.recording, "scan": it.index, "artifact": it.placement.artifact,
                     "settings": it.scan.settings.label(), "position": "fitted" if it.placement.fitted else "known",
                     **it.figures.to_dict()} for it in data.scans]
    report: dict[str, Any] = {
        "schema": "xmetro-calibration-report/1",
        "campaign": camp.card(),
        "checks": data.checks.to_dict(),
        "positions": card_extra["positions"],
        "vdi2634": {"per_measurement": probing_rows, "spacing": data.spacing,
                    "per_settings": vdi2634.summarize([*probing_rows, *data.spacing])},
        "models": {s: metrics["splits"][s]["models"] for s in metrics["splits"]},
        "model_dirs": {fam: str(d) for fam, d in model_dirs.items()},
        "uncertainty": {"split": "by scan (seeded): " + ", ".join(f"{len(v)} measurements {k}" for k, v in
                                                                    parts.items()),
                        "held_out": split_doc, "families": unc},
        "prior": None if warm is None else warm.to_dict(),
    }
    maps = deviation_maps(data, parts, model_dirs, out, seed=seed)
    report["deviation_maps"] = [{k: v for k, v in m.items() if k != "png_b64"} for m in maps]
    report["wall_s"] = round(time.perf_counter() - t0, 1)
    (out / "report.json").write_text(json.dumps(report, indent=2, default=float))
    (out / "report.md").write_text(markdown(report))
    write_html(out / "report.html", report, maps)
    log(f"wrote {out / 'report.html'}, report.md, report.json and model sets under {out / 'models'} "
        f"({report['wall_s']:.0f} s)")
    return report


def run(args: argparse.Namespace) -> int:
    """``xmetro calibrate``: returns the exit code (2 with the reason on a campaign error)."""
    from ..calibrate.campaign_file import CampaignError
    from ..calibrate.profile_campaign import PROFILE_CAMPAIGN_FORMAT, campaign_format
    from ..scan.profiles import ProfileDataError

    fams = tuple(f.strip() for f in args.families.split(",") if f.strip())
    try:
        if Path(args.campaign).is_file() and campaign_format(args.campaign) == PROFILE_CAMPAIGN_FORMAT:
            from .calibrate_profiles import calibrate_profiles

            calibrate_profiles(args.campaign, args.out, iterations=args.iterations, seed=args.seed)
            return 0
        calibrate(args.campaign, args.out, profile=args.profile, families=fams, seed=args.seed,
                  max_points=args.max_points, uncertainty=not args.no_uncertainty, prior=args.prior)
    except (CampaignError, ProfileDataError, ValueError, FileNotFoundError) as e:
        print(f"xmetro calibrate: error: {e}", file=sys.stderr)
        return 2
    return 0
