"""`xmetro train` (the study's pipeline) and `xmetro export-default` (the shipped default model set)."""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import warnings
from pathlib import Path
from typing import Any

from ..learn.families import FAMILIES, PROFILES

__all__ = ["DEFAULT_FAMILY", "register", "run_export_default", "run_train"]

DEFAULT_FAMILY = "pointnet_multi"  # compact 3-axis PointNet: the node's default (fast enough for a 180k scan)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``xmetro train`` and ``xmetro export-default`` to the ``xmetro`` sub-commands."""
    p = subparsers.add_parser("train", help="run the study's learning pipeline (metrics, tables, SHAP, ONNX)")
    p.add_argument("--profile", choices=sorted(PROFILES), default="quick",
                   help="quick: < 2 min smoke run; full: the study's protocol; micro: tests")
    p.add_argument("--out", required=True, help="output directory (metrics.json, tables.md, PNGs, models/)")
    p.add_argument("--data", default=None, help="directory (or file) of simulated scans (.mcap from `xmetro "
                   "simulate`); default: simulate the profile's campaign with --seed")
    p.add_argument("--seed", type=int, default=0, help="seed of the campaign, the splits and the fits (default 0)")
    p.add_argument("--families", default=",".join(FAMILIES), help=f"comma-separated subset of {','.join(FAMILIES)}")
    p.add_argument("--threads", type=int, default=1, help="threads per fit (torch, BLAS, CatBoost)")
    p.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                   help="prepare the data (simulate/read, pre-process, features, targets) on this Dask cluster")
    p.add_argument("--workers", type=int, default=None,
                   help="prepare the data on a local Dask cluster of this many worker processes (same table)")
    p.set_defaults(func=run_train)

    e = subparsers.add_parser("export-default", help="train (or copy) the default model set shipped in the package")
    e.add_argument("--seed", type=int, default=0, help="seed of the campaign, the splits and the fits (default 0)")
    e.add_argument("--profile", choices=sorted(PROFILES), default="full",
                   help="run profile of the training (default full: the study's protocol)")
    src = e.add_mutually_exclusive_group()
    src.add_argument("--from", dest="from_dir", default=None,
                     help=f"copy <DIR>/models/{DEFAULT_FAMILY} of a finished `xmetro train` run")
    src.add_argument("--from-packaged", action="store_true",
                     help="copy the packaged model set (to calibrate it again)")
    src.add_argument("--from-model", default=None, metavar="DIR",
                     help="copy the model set in DIR (e.g. xmetro_ros/models/posed)")
    dest = e.add_mutually_exclusive_group(required=True)
    dest.add_argument("--out", default=None, help="target directory")
    dest.add_argument("--replace-packaged", action="store_true",
                      help="replace models/default in the package (never done without it)")
    e.add_argument("--no-calibrate", action="store_true",
                   help="skip the conformal calibration (the card then has no 'uncertainty')")
    e.add_argument("--no-surfaces", action="store_true",
                   help="calibrate on the campaign's shapes only (cards up to 0.7.2)")
    e.add_argument("--add-surfaces", action="store_true",
                   help="keep the card's calibration; add the surfaces' per-class U and shape domain")
    e.add_argument("--along-normal", action="store_true",
                   help="calibrate d and U along the measured normal too (card uncertainty.along_normal; without "
                        "it the card gets none, the shipped card's included)")
    e.add_argument("--cover-sources", action="store_true",
                   help="per-class cells cover each sigma source's rows on their own (models/posed)")
    e.set_defaults(func=run_export_default)


def _families(text: str) -> tuple[str, ...]:
    from ..learn.families import check_family

    fams = tuple(f.strip() for f in text.split(",") if f.strip())
    if not fams:
        raise ValueError("--families is empty")
    for f in fams:
        check_family(f)
    return fams


def warning_summary(records: list[warnings.WarningMessage]) -> list[str]:
    """One line per kind of warning the training libraries raised (category, count, first message), instead of
    one line per fit: an MLP that stops at max_iter warns in every fold of every search candidate."""
    kinds: dict[tuple[str, str], list[str]] = {}
    for w in records:
        first = str(w.message).splitlines()[0] if str(w.message) else ""
        kinds.setdefault((w.category.__name__, first[:160]), []).append(w.filename)
    return [f"{cat} x{len(v)}: {msg}" for (cat, msg), v in sorted(kinds.items(), key=lambda kv: -len(kv[1]))]


def run_train(args: argparse.Namespace) -> int:
    """``xmetro train``: load or simulate the data, run the study, write its results; returns the exit code.
    Warnings of the training libraries are collected and printed once per kind at the end (stderr)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rc = _run_train(args)
    for line in warning_summary(list(caught)):
        print(f"xmetro train: warning: {line}", file=sys.stderr)
    return rc


def _run_train(args: argparse.Namespace) -> int:
    from ..learn.study import load_data, run_study

    try:
        fams = _families(args.families)
        if args.scheduler or args.workers:
            table, manifest = _load_data_dask(args)
        else:
            scans, source = _read_data(args.data) if args.data else (None, None)
            table, manifest = load_data(args.profile, args.seed, scans=scans, source_manifest=source)
        metrics = run_study(table, manifest, args.profile, args.seed, args.out, families=fams,
                            threads=args.threads, card_extra={"scanner": _scanner_card()})
    except (ValueError, FileNotFoundError) as e:
        print(f"xmetro train: error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {Path(args.out) / 'metrics.json'} and {Path(args.out) / 'tables.md'} "
          f"({metrics['timings_s']['total']:.0f} s)")
    return 0


CALIBRATION_SEED_OFFSET = 1000  # calibration clouds: the profile's campaign simulated with seed + this
# Points drawn per calibration cloud: enough for a multiplier per condition (incidence bin x exposure level), ~180
# points per exposure level even beyond 80 deg incidence (0.25 % of a sphere scan's points).
CALIBRATION_POINTS_PER_CLOUD = 2000


def _calibrate_default(model_dir: Path, profile: str, seed: int, surfaces: bool = True,
                       keep_calibration: bool = False, by_source: bool = False, along_normal: bool = False) -> None:
    """Split-conformal calibration of the default model set on clouds it never saw: the profile's campaign
    simulated again with seed + CALIBRATION_SEED_OFFSET (same artifacts, settings and head poses, new clouds) and,
    with ``surfaces``, the calibration surfaces (plates, grooves, a saddle, a filleted ridge at many tilts:
    scan/calibration_surfaces.py) under the study's settings, from the campaign's head poses when it has some
    (cycled as the campaign cycles them: "calibrate where the model judges"); CALIBRATION_POINTS_PER_CLOUD points
    per cloud, per axis, per condition (learn/uncertainty.py) and per surface class (judge/surface_class.py), the
    latter on max(σ̂, measured noise·|N|) (judge/measured_noise.py). The shape domain (card ``domain_shape``: mean
    curvature range and the (κmin, κmax) cells) comes from the same clouds.

    ``keep_calibration`` (with ``surfaces``): the card keeps its all-class multipliers and conditions and its
    multivariate domain (the recommender's U and domain: its figures do not move) and gains the per-class block
    (``uncertainty.conditional.by_surface``) and the shape domain; ValueError when the card's conditions are not
    those the new block is laid out on. ``by_source``: the per-class multipliers cover each σ source's rows on
    their own (learn/uncertainty.py ``conditional_multipliers``). ``along_normal`` (with ``surfaces``): the card's U
    also gets the ``along_normal`` block (judge/along_normal.py: d and U carried onto the measured normal)."""
    import numpy as np

    from ..judge.features import STUDY_FEATURES
    from ..judge.inference import update_card
    from ..learn.calibration_set import calibration_set
    from ..learn.families import get_profile
    from ..learn.shape_domain import fit_principal_domain, fit_shape_domain
    from ..learn.uncertainty import calibrate, fit_domain
    from ..scan.calibration_surfaces import surface_campaign
    from ..sim import simulate_scan
    from ..sim.campaign import campaign_pose, study_campaign

    if keep_calibration and not surfaces:
        raise ValueError("keeping the card's calibration adds the surfaces' blocks: it needs the surfaces")
    if along_normal and not surfaces:
        raise ValueError("U along the normal is calibrated per surface class on the measured noise: it needs the "
                         "surfaces")
    prof = get_profile(profile)
    cal_seed = seed + CALIBRATION_SEED_OFFSET
    items = study_campaign(seed=cal_seed, **dict(prof.campaign))
    scanner = items[0].scanner if items else None
    scans = [it.simulate() for it in items]
    labels: list[str] = []
    if surfaces:
        from ..scan.scanner import ScannerModel

        sc = scanner or ScannerModel.load()
        # micro (tests): every 13th setting of each surface, 3 of 27 spanning the three exposures
        stride = 13 if profile == "micro" else 1
        surf = surface_campaign(sc, cal_seed, stride=stride)
        poses = prof.campaign.get("poses")
        per_surface = len(sc.study_configurations()[::stride])  # surface_campaign: each surface's settings in turn
        for i, (a, st, sd, lab) in enumerate(surf):
            pose, where = None, ""
            if poses:  # setting c of surface s from head pose (c + s) mod P, as study_campaign's cycle
                s, c = divmod(i, per_surface)
                k = (c + s) % len(poses)
                pose, where = campaign_pose(a, np.asarray(poses[k], np.float64), sc), f" head pose {k}"
            scans.append(simulate_scan(a, st, scanner=sc, seed=sd, pose=pose))
            labels.append(f"calibration surfaces seed {cal_seed}: {lab}{where}")
    cs = calibration_set(scans, list(STUDY_FEATURES), max_points_per_cloud=CALIBRATION_POINTS_PER_CLOUD,
                         seed=cal_seed, scanner=scanner)
    t = cs.table
    labels = [f"campaign seed {cal_seed} item {i}: {c['label']} {c['artifact']['kind']}"
              for i, c in enumerate(t.clouds[: len(items)])] + labels
    block = calibrate(model_dir, t.X, t.y, t.cloud_id, cloud_labels=labels, write=not keep_calibration,
                      surface_class=cs.surface_class if surfaces else None, noise=cs.noise if surfaces else None,
                      by_source=by_source, along_normal=along_normal, tilt=cs.tilt if along_normal else None)
    shape = fit_shape_domain(cs.mean_curvature)
    extra: dict[str, Any] = {}
    if surfaces:
        shape["principal"] = fit_principal_domain(cs.principal)
    if keep_calibration:  # calibrate wrote nothing: the card still holds its own block
        card = json.loads((Path(model_dir) / "card.json").read_text())
        extra["uncertainty"] = _with_surface_block(card.get("uncertainty"), block, labels)
        # the along-normal block is fitted on these rows too: a new one, or none (never the card's old one)
        extra["uncertainty"].pop("along_normal", None)
        if "along_normal" in block:
            extra["uncertainty"]["along_normal"] = block["along_normal"]
    elif surfaces:
        # U is calibrated on these rows without any widening: the multivariate domain (where U is widened and the
        # point flagged) is theirs, the training campaign's shapes and the surfaces', not the training rows' alone
        extra["domain_mv"] = {**fit_domain(t.X), "fitted_on": "the calibration rows (training campaign simulated "
                              "again and the calibration surfaces), where U is calibrated"}
    update_card(model_dir, domain_shape=shape, **extra)
    print(f"calibrated on {len(scans)} clouds: multipliers {[round(k, 3) for k in block['multiplier']]}"
          + (" (not written: the card's are kept)" if keep_calibration else "")
          + f"; shape domain: mean curvature {shape['lo']:.4f} to {shape['hi']:.4f} /mm"
          + (f", {len(shape['principal']['cells'])} (kmin, kmax) cells" if surfaces else ""))


def _with_surface_block(old: dict[str, Any] | None, block: dict[str, Any], labels: list[str]) -> dict[str, Any]:
    """The card's ``uncertainty`` block ``old`` with the per-surface-class multipliers of a new calibration
    ``block`` (``conditional.by_surface``, labelled with the clouds it came from) and its U formula; ValueError when
    ``old`` has no conditional multipliers or other conditions (incidence, exposure edges) than ``block``."""
    import copy

    new_cond = block.get("conditional") or {}
    if not old or not old.get("conditional"):
        raise ValueError("the card has no conditional U to add per-class multipliers to: calibrate it in full")
    if "by_surface" not in new_cond:
        raise ValueError("the calibration gave no per-class multipliers (no surface classes in its rows)")
    cond = old["conditional"]
    for key in ("incidence_edges_deg", "exposure_edges_ms"):
        if [float(v) for v in cond[key]] != [float(v) for v in new_cond[key]]:
            raise ValueError(f"the card's conditions ({key} {cond[key]}) are not the new block's ({new_cond[key]})")
    out = copy.deepcopy(old)
    out["conditional"]["by_surface"] = {**new_cond["by_surface"], "calibration_clouds": labels,
                                        "added": "to the card's own calibration (xmetro export-default "
                                                 "--add-surfaces): all-class multipliers and domain_mv kept"}
    out["U"] = block["U"]
    return out


def run_export_default(args: argparse.Namespace) -> int:
    """``xmetro export-default``: train (or copy) a model set, check it loads, install it; exit code."""
    from ..judge.inference import ModelSet
    from ..scan.resources import default_model_dir

    target = default_model_dir() if args.replace_packaged else Path(args.out)
    with tempfile.TemporaryDirectory() as tmp:
        if args.from_packaged:
            src = default_model_dir()
        elif args.from_dir:
            src = Path(args.from_dir) / "models" / DEFAULT_FAMILY
        elif args.from_model:
            src = Path(args.from_model)
        else:
            from ..learn.study import load_data, run_study

            table, manifest = load_data(args.profile, args.seed)
            run_study(table, manifest, args.profile, args.seed, tmp, families=(DEFAULT_FAMILY,),
                      card_extra={"scanner": _scanner_card(),
                                  "trained_by": f"xmetro export-default --profile {args.profile} --seed {args.seed}"
                                  + ("" if args.no_calibrate else " (calibrated on the campaign simulated with "
                                     f"seed {args.seed + CALIBRATION_SEED_OFFSET})")})
            src = Path(tmp) / "models" / DEFAULT_FAMILY
        staged = Path(tmp) / "staged"
        shutil.copytree(src, staged)  # calibration writes the card: never into the --from directory
        src = staged
        if args.add_surfaces and args.no_calibrate:  # with --no-surfaces, _calibrate_default says why
            print("xmetro export-default: error: --add-surfaces calibrates: not with --no-calibrate", file=sys.stderr)
            return 2
        if not args.no_calibrate:
            try:
                _calibrate_default(src, args.profile, args.seed, surfaces=not args.no_surfaces,
                                   keep_calibration=args.add_surfaces, by_source=args.cover_sources,
                                   along_normal=args.along_normal)
            except ValueError as e:
                print(f"xmetro export-default: error: {e}", file=sys.stderr)
                return 2
        ms = ModelSet.load(src)  # validates before replacing the shipped model
        if target.exists():
            shutil.rmtree(target)
        shutil.copytree(src, target)
    card = json.loads((target / "card.json").read_text())
    print(f"default model {card['id']} → {target} ({ms})")
    return 0


def _read_data(data: str | Path) -> tuple[list[Any], dict[str, Any]]:
    """Scans of ``--data`` (a bag written by ``xmetro simulate`` or a directory of them) and their manifest."""
    from ..ros.scan_io import read_manifest, read_scans

    files = _data_files(data)
    scans: list[Any] = []
    manifest: dict[str, Any] = {}
    for f in files:
        scans += read_scans(f)
        manifest = read_manifest(f) or manifest
    return scans, {"source": "files", "files": [f.name for f in files], "campaign": manifest}


def _scanner_card() -> dict[str, str]:
    """The scanner a simulated campaign stands for (the packaged virtual scanner)."""
    from ..scan.scanner import ScannerModel

    sc = ScannerModel.load()
    return {"id": sc.id, "serial": sc.serial, "description": sc.source, "virtual": "true"}


class BagScans:
    """A Dask source: the scans of one bag written by ``xmetro simulate``, read on the worker."""

    def __init__(self, path: str | Path) -> None:
        self.path = str(path)

    def __call__(self) -> list[Any]:
        from ..ros.scan_io import read_scans

        return read_scans(self.path)

    def __repr__(self) -> str:
        return f"BagScans({self.path!r})"


def _data_files(data: str | Path) -> list[Path]:
    d = Path(data)
    files = sorted(d.glob("*.mcap")) if d.is_dir() else [d]
    if not files:
        raise FileNotFoundError(f"no .mcap scans in {d}")
    return files


def _load_data_dask(args: argparse.Namespace) -> tuple[Any, dict[str, Any]]:
    """``load_data`` with the data preparation on Dask (``--scheduler`` or a local ``--workers`` cluster)."""
    from ..learn.study import load_data
    from ..ros.scan_io import read_manifest
    from .fleet import dask_client

    sources, source = None, None
    if args.data:
        files = _data_files(args.data)
        manifest: dict[str, Any] = {}
        for f in files:
            manifest = read_manifest(f) or manifest
        sources = [BagScans(f.resolve()) for f in files]
        source = {"source": "files", "files": [f.name for f in files], "campaign": manifest}
    with dask_client(args.scheduler, args.workers) as client:
        return load_data(args.profile, args.seed, source_manifest=source, client=client, sources=sources)
