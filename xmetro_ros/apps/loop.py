"""`xmetro loop INPUT... --artifact SPEC --out DIR` or `xmetro loop --campaign CAMPAIGN.yaml --out DIR`: close the
loop on measured or recorded data, or on a calibration campaign (several artifacts, known or fitted positions)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["register", "run"]


def register(subparsers) -> None:
    """Add ``xmetro loop`` to the ``xmetro`` sub-commands."""
    p = subparsers.add_parser("loop", help="trace the residual of the model to an undeclared effect and add it",
                              description=__doc__)
    p.add_argument("inputs", nargs="*", help="MCAP bags, NIST .xyz files/dir, the AT C5 profile dir, or .txt lists "
                   "of laser-line profile files (sphere only)")
    p.add_argument("--campaign", default=None, help="calibration campaign file (xmetro-campaign/1) instead of inputs")
    p.add_argument("--artifact", default=None, help="nominal artifact, e.g. sphere:radius=50,center=fit")
    p.add_argument("--out", required=True, help="output directory (report.json, report.md, plots, model/)")
    p.add_argument("--model", default=None, help="model dir (ModelSet); default: retrain CatBoost on the input")
    p.add_argument("--candidates", default=None, help="comma-separated candidate names (default: all)")
    p.add_argument("--correction", default="auto", choices=["auto", "feature", "offset"],
                   help="auto: identities become per-identity offsets, other variables features; else only that kind")
    p.add_argument("--max-iter", type=int, default=3, help="at most this many effects added (default 3)")
    p.add_argument("--n-perm", type=int, default=199, help="permutations of each candidate's null (default 199)")
    p.add_argument("--alpha", type=float, default=0.01, help="family-wise level of the Holm-corrected tests "
                   "(default 0.01)")
    p.add_argument("--min-effect", type=float, default=0.05,
                   help="smallest share of the residual's variance an identity must explain (default 0.05)")
    p.add_argument("--iterations", type=int, default=300, help="boosting iterations of the retrained family")
    p.add_argument("--seed", type=int, default=0, help="seed of the role draw, the model and the trace (default 0)")
    p.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                   help="prepare the inputs (read, pre-process, features, targets) on this Dask cluster")
    p.add_argument("--workers", type=int, default=None,
                   help="prepare the inputs on a local Dask cluster of this many worker processes (same data)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """``xmetro loop``: load the inputs, run the loop, write the report (and the augmented model); exit code."""
    from ..calibrate.campaign_file import CampaignError
    from ..loop.data import LoopInputError
    from ..loop.inputs import load_inputs
    from ..loop.model import GivenModel
    from ..loop.report import write_report
    from ..loop.run import LoopConfig, run_loop
    from ..loop.trace import TraceConfig
    from ..ros.scan_io import iter_scans
    from ..scan.artifacts import ArtifactSpecError

    try:
        given = None
        if args.model:
            from ..judge.inference import ModelSet

            given = GivenModel(ModelSet.load(args.model))
        feats = given.feature_names if given else None
        if args.campaign:
            if args.inputs or args.artifact:
                raise LoopInputError("--campaign names its recordings and artifacts: give no inputs or --artifact")
            if args.workers or args.scheduler:
                raise LoopInputError("--workers / --scheduler prepare bag and measured inputs: a --campaign is "
                                     "read in this process")
            from ..loop.inputs import from_campaign

            data = from_campaign(args.campaign, _read_recording, feats)
        elif args.workers or args.scheduler:
            from ..loop.inputs_dask import load_inputs_dask
            from .fleet import dask_client

            with dask_client(args.scheduler, args.workers) as client:
                data = load_inputs_dask(args.inputs, args.artifact, feats, client, read_bag=iter_scans,
                                        progress=lambda s: print(s, file=sys.stderr, flush=True))
        else:
            data = load_inputs(args.inputs, args.artifact, feats, read_bag=iter_scans)
        cfg = LoopConfig(
            iterations=args.iterations, max_iter=args.max_iter, correction=args.correction, seed=args.seed,
            candidates=args.candidates.split(",") if args.candidates else None,
            trace=TraceConfig(n_perm=args.n_perm, alpha=args.alpha, min_effect=args.min_effect, seed=args.seed),
        )
        result = run_loop(data, cfg, given)
        path = write_report(result, args.out)
        if result.added_features:
            from ..loop.export import export_loop_model

            try:
                export_loop_model(result, data, Path(args.out) / "model")
            except LoopInputError as e:  # derived (non-registry) features: report stays valid, no model dir
                print(f"xmetro loop: model not exported: {e}", file=sys.stderr)
    except (ArtifactSpecError, CampaignError, LoopInputError, ValueError, OSError, RuntimeError) as e:
        print(f"xmetro loop: error: {e}", file=sys.stderr)
        return 2
    sel = result.report["selected"]
    diag = [f["variable"] for f in result.report["diagnostic"]["findings"]]
    print(f"predictive: {sel['name'] if sel else 'none'}; diagnostic: {', '.join(diag) if diag else 'none'}; "
          f"report: {path}")
    return 0


def _read_recording(rec, scanner):
    """A campaign recording's scans (its own topics), as ``xmetro calibrate`` reads them."""
    from ..ros.scan_io import read_scans

    return read_scans(rec.bag, topic=rec.scan_topic, settings_topic=rec.settings_topic, scanner=scanner)
