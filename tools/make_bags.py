#!/usr/bin/env python3
"""Regenerate the shipped demo / regression bags (virtual scanner) and their golden outputs.

    python tools/make_bags.py                 # bags/demo.mcap, bags/regression.mcap and bags/golden/*
    python tools/make_bags.py --golden-only   # only the goldens (after a model or processing change)

Bags: scans of the study's artifacts (spheres of diameter 35, 45, 55 mm and a cylinder) by the virtual scanner
(``xmetro_ros.sim.simulate_scan``), each with its ScannerSettings message, written by ``scan_io.write_scans``. The
settings are study levels at the low-density end so that each bag stays well under 5 MB.

Goldens: ``bags/golden/<bag>.mcap`` = the outputs of ``xmetro predict`` (the node's processing path, offline) for
the shipped default model, and ``bags/golden/golden.json`` = model id, input bag digests, the comparison tolerance
and a per-scan summary. test/test_replay_golden.py replays the bags through a live node and compares its outputs
with these goldens within the stated tolerance.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from xmetro_ros.scan.artifacts import Cylinder, Sphere  # noqa: E402
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings  # noqa: E402

# Scans are stamped from this epoch (2025-01-01T00:00:00Z), one every STAMP_STEP_NS.
STAMP0_NS = 1_735_689_600_000_000_000
STAMP_STEP_NS = 2_000_000_000

# (artifact, settings (lateral /mm, direction /mm, exposure ms)) per bag.
BAGS: dict[str, list[tuple[str, tuple[float, float, float]]]] = {
    "demo": [
        ("sphere:d=35", (6.0, 3.0, 0.5)),
        ("sphere:d=45", (6.0, 3.0, 0.1)),
        ("sphere:d=55", (6.0, 3.0, 2.0)),
        ("cylinder:d=40", (6.0, 3.0, 0.5)),
    ],
    "regression": [
        ("sphere:d=45", (6.0, 3.0, 0.5)),
        ("sphere:d=35", (10.0, 4.0, 2.0)),
        ("sphere:d=35", (6.0, 5.0, 0.1)),
        ("cylinder:d=40", (6.0, 4.0, 0.5)),
    ],
}
SEED = 7

# Golden comparison tolerance (live node vs golden): see docs/replay.md.
TOLERANCE = {
    "deviation_atol_m": 1e-7,        # 0.1 µm on each predicted deviation component
    "quality_atol_m": 1e-7,          # mean / p95 |error| per axis
    "fraction_atol": 1e-3,           # usable_fraction
    "flags_max_mismatch_fraction": 0.002,  # share of points whose flags may differ (thresholds hit by rounding)
}


def make_artifact(spec: str):
    kind, _, arg = spec.partition(":")
    d = float(arg.split("=")[1])
    if kind == "sphere":
        return Sphere(radius=d / 2.0, center=(0.0, 0.0, 0.0))
    if kind == "cylinder":
        return Cylinder(radius=d / 2.0, center=(0.0, 0.0, 0.0))
    raise ValueError(f"unknown artifact spec {spec!r}")


def make_scans(name: str, scanner: ScannerModel) -> list:
    from xmetro_ros.sim import simulate_scan

    scans = []
    for i, (spec, s) in enumerate(BAGS[name]):
        settings = ScanSettings(*s)
        scan = simulate_scan(make_artifact(spec), settings, scanner=scanner, seed=SEED + i, frame_id="artifact",
                             stamp_ns=STAMP0_NS + i * STAMP_STEP_NS)
        scan.meta = {**scan.meta, "bag": name, "artifact_spec": spec, "settings_label": settings.label()}
        scans.append(scan)
    return scans


def write_bag(name: str, out_dir: Path, scanner: ScannerModel) -> Path:
    from xmetro_ros.ros.scan_io import write_scans

    path = out_dir / f"{name}.mcap"
    scans = make_scans(name, scanner)
    manifest = {
        "generator": "tools/make_bags.py",
        "bag": name,
        "seed": SEED,
        "scanner": scanner.id,
        "scans": [{"artifact": spec, "settings": list(s), "stamp_ns": STAMP0_NS + i * STAMP_STEP_NS}
                  for i, (spec, s) in enumerate(BAGS[name])],
    }
    path.unlink(missing_ok=True)
    write_scans(path, scans, manifest=manifest)
    return path


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def write_goldens(out_dir: Path, names: list[str], model_dir: Path | None = None) -> dict:
    from xmetro_ros.apps.predict import predict_bag

    golden_dir = out_dir / "golden"
    golden_dir.mkdir(parents=True, exist_ok=True)
    doc: dict = {"generator": "tools/make_bags.py", "tolerance": TOLERANCE, "bags": {}}
    for name in names:
        bag = out_dir / f"{name}.mcap"
        target = golden_dir / f"{name}.mcap"
        target.unlink(missing_ok=True)
        res = predict_bag(bag, target, model_dir=model_dir, include=("deviations",))
        doc["model_id"] = res.model_id
        doc["bags"][name] = {
            "input_sha256": sha256(bag),
            "scans": [o.summary_dict() for o in res.outputs],
        }
        print(res.summary())
    (golden_dir / "golden.json").write_text(json.dumps(doc, indent=1) + "\n")
    return doc


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=ROOT / "bags", help="output directory (default: bags/)")
    ap.add_argument("--golden-only", action="store_true", help="only recompute bags/golden/* from the bags")
    ap.add_argument("--model", type=Path, default=None, help="model dir (default: the shipped default model)")
    ap.add_argument("--bag", action="append", choices=sorted(BAGS), help="only this bag (repeatable)")
    args = ap.parse_args(argv)
    names = args.bag or sorted(BAGS)
    args.out.mkdir(parents=True, exist_ok=True)
    if not args.golden_only:
        scanner = ScannerModel.load()
        for name in names:
            p = write_bag(name, args.out, scanner)
            size = p.stat().st_size
            print(f"wrote {p} ({size / 1e6:.2f} MB)")
            if size > 5e6:
                print(f"error: {p} is over 5 MB", file=sys.stderr)
                return 1
    write_goldens(args.out, names, args.model)
    return 0


if __name__ == "__main__":
    sys.exit(main())
