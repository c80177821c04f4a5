"""`xmetro fleet predict BAGS... --out-dir DIR`: re-judge a fleet's recordings on Dask distributed.

Each input bag is one task that runs :func:`xmetro_ros.apps.predict.predict_bag` — the very function of
``xmetro predict`` — on a Dask worker; so an output bag is the one ``xmetro predict`` writes for the same bag,
model and parameters: byte for byte with ``--deterministic`` (``processing_latency``, the one wall-clock value of
the outputs, written as 0, and the CDR padding zeroed); without it every field but ``processing_latency``.
The scheduler is a local cluster of worker processes (one per core by default, ``--workers N``) or an existing
cluster (``--scheduler tcp://host:8786``): the same code path. Workers must see the input and output paths (a
shared file system on a multi-machine cluster).

Outputs in ``--out-dir``:

- ``<bag>.mcap`` per input bag (its path relative to the inputs' common directory, so two cells' bags of one name
  do not collide) and ``<bag>.scans.parquet`` (its per-scan quality rows);
- ``summary.parquet``: every scan of every bag (bag, cell, time, verdict, error code, per-axis errors and
  uncertainty, settings, counts: see :func:`~xmetro_ros.apps.fleet_report.quality_row`), readable with
  ``pandas.read_parquet`` or ``dask.dataframe.read_parquet``;
- ``overview.html``: verdict shares and p95 error per cell over time (PNGs embedded), and the bags' statuses
  (the summary and the overview are written by ``apps/fleet_report.py``);
- ``fleet.json``: per-bag status (done / skipped / failed with the error / damaged with the data lost), timings,
  each worker's peak resident memory.

Failures of one bag (unreadable, no scans, a crashed worker) are reported and the others complete. A bag is done
when both its output files exist: they are written under temporary names and renamed at the end, so a killed run
leaves no half output under a final name and a new run with the same arguments skips the done bags (``--redo``
recomputes them).
"""

from __future__ import annotations

import argparse
import contextlib
import fnmatch
import glob
import json
import os
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .fleet_report import AXES, BagJob, count_rows, frame, quality_row, write_overview, write_summary

__all__ = ["AXES", "BagJob", "FleetResult", "dask_client", "find_bags", "plan_jobs", "predict_job", "quality_row",
           "register", "run", "run_fleet", "write_overview", "write_summary"]
SCANS_SUFFIX = ".scans.parquet"
SUMMARY = "summary.parquet"
OVERVIEW = "overview.html"
STATUS = "fleet.json"


@dataclass
class FleetResult:
    """What a fleet run did, bag by bag (``status``: done, skipped, damaged or failed)."""

    bags: list[dict[str, Any]] = field(default_factory=list)
    summary: Path | None = None
    overview: Path | None = None
    wall_s: float = 0.0
    workers: int = 0

    def count(self, status: str) -> int:
        return sum(1 for b in self.bags if b["status"] == status)

    @property
    def lost_data(self) -> int:
        """Bags whose input lost data: damaged in this run, or skipped after a run that found them damaged."""
        return sum(1 for b in self.bags if b["status"] == "damaged" or b.get("damaged"))

    @property
    def scans(self) -> int:
        return sum(int(b.get("scans", 0)) for b in self.bags if b["status"] in ("done", "damaged"))


# ---------------------------------------------------------------------------------------------------- inputs
def find_bags(inputs: list[str]) -> list[Path]:
    """The bags named by ``inputs``: .mcap files, rosbag2 directories (holding ``metadata.yaml``), directories
    searched recursively for both, and glob patterns of any of these. Sorted, duplicates removed.

    Raises:
        FileNotFoundError: an input matches nothing.
    """
    found: list[Path] = []
    for item in inputs:
        paths = [Path(p) for p in sorted(glob.glob(item, recursive=True))] if glob.has_magic(item) else [Path(item)]
        if not paths or not all(p.exists() for p in paths):
            raise FileNotFoundError(f"no bag at {item}")
        for p in paths:
            if p.is_file():
                found.append(p)
            elif (p / "metadata.yaml").is_file():
                found.append(p)
            else:
                for root, dirs, files in os.walk(p):
                    r = Path(root)
                    if (r / "metadata.yaml").is_file():
                        found.append(r)
                        dirs[:] = []
                        continue
                    dirs.sort()
                    found += [r / f for f in sorted(files) if f.endswith(".mcap")]
    out, seen = [], set()
    for p in found:
        k = p.resolve()
        if k not in seen:
            seen.add(k)
            out.append(p)
    return sorted(out, key=lambda p: str(p.resolve()))


def _cell_of(bag: Path, cells: list[tuple[str, str]]) -> str:
    """The first ``--cell PATTERN=NAME`` whose pattern matches the bag's path; else the bag's directory name."""
    for pattern, name in cells:
        if fnmatch.fnmatch(str(bag), pattern) or fnmatch.fnmatch(str(bag.resolve()), pattern):
            return name
    return bag.resolve().parent.name


def plan_jobs(bags: list[Path], out_dir: str | Path, cells: list[tuple[str, str]] | None = None) -> list[BagJob]:
    """One job per bag (absolute paths); output names keep each bag's path relative to the bags' common
    directory."""
    if not bags:
        raise FileNotFoundError("no input bags")
    out_dir = Path(out_dir).resolve()  # absolute paths: a worker's working directory is not ours
    resolved = [b.resolve() for b in bags]
    common = Path(os.path.commonpath([str(r.parent) for r in resolved]))
    jobs = []
    for b, r in zip(bags, resolved, strict=True):
        rel = r.relative_to(common)
        name = str(rel.with_suffix("")) if rel.suffix == ".mcap" else str(rel)
        jobs.append(BagJob(bag=str(r), name=name, out=str(out_dir / f"{name}.mcap"),
                           scans=str(out_dir / f"{name}{SCANS_SUFFIX}"), cell=_cell_of(b, cells or [])))
    names = [j.name for j in jobs]
    if len(set(names)) != len(names):
        raise ValueError("two input bags map to the same output name")
    return jobs


# ---------------------------------------------------------------------------------------------------- one bag
def _peak_rss_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def damage_record(out: str | Path) -> Path:
    """The file beside a bag's output that records the data its input lost (``<out>.losses.json``)."""
    return Path(f"{out}.losses.json")


def predict_job(job: BagJob, model_dir: str | None = None, params: dict[str, Any] | None = None,
                topics: list[str] | None = None, deterministic: bool = False) -> dict[str, Any]:
    """Judge one bag (the Dask task): ``predict_bag`` into temporary names, the per-scan rows to Parquet, then
    both renamed to their final names. Never raises: returns the bag's status record (``failed`` + ``error``)."""
    from .predict import predict_bag

    t0, c0 = time.monotonic(), time.process_time()
    rec: dict[str, Any] = {"bag": job.bag, "name": job.name, "cell": job.cell, "out": job.out,
                           "worker_pid": os.getpid()}
    out, scans = Path(job.out), Path(job.scans)
    # The bag's own name is recorded inside it (rosbag2 metadata: relative_file_paths), so the temporary file
    # keeps the final name, in a side directory.
    tmp_out = out.parent / ".partial" / out.name
    tmp_scans = out.parent / ".partial" / scans.name
    try:
        tmp_out.parent.mkdir(parents=True, exist_ok=True)
        for p in (tmp_out, tmp_scans, out, scans):  # a previous run's leftovers, or a --redo
            p.unlink(missing_ok=True)
        res = predict_bag(job.bag, tmp_out, model_dir=model_dir, params=params, topics=topics,
                          keep_clouds=False, deterministic=deterministic)
        rows = []
        for i, (o, topic) in enumerate(zip(res.outputs, res.inputs, strict=True)):
            r = {"bag": job.name, "cell": job.cell, "scan": i, "topic": topic}
            r.update(quality_row(o.quality))
            rows.append(r)
        frame(rows).to_parquet(tmp_scans, index=False)
        damage = damage_record(out)
        if res.losses:  # kept beside the outputs: a later run that skips this bag still reports what was lost
            damage.write_text(json.dumps({"bag": job.bag, "losses": res.losses}, indent=1))
        else:
            damage.unlink(missing_ok=True)
        os.replace(tmp_scans, scans)
        os.replace(tmp_out, out)  # last: the .mcap under its final name marks the bag done
        with contextlib.suppress(OSError):
            tmp_out.parent.rmdir()  # when no other bag of this directory is under way
        verdicts = [str(r["verdict_name"]) for r in rows]
        rec.update(status="damaged" if res.losses else "done", scans=len(rows), model_id=res.model_id,
                   verdicts={v: verdicts.count(v) for v in sorted(set(verdicts))},
                   losses=res.losses, notes=res.notes)
    except Exception as e:  # one bag's failure must not stop the fleet: reported in its record
        for p in (tmp_out, tmp_scans):
            with contextlib.suppress(OSError):
                p.unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            tmp_out.parent.rmdir()  # no empty .partial/ left behind
        rec.update(status="failed", error=f"{type(e).__name__}: {e}", scans=0)
    rec["wall_s"] = time.monotonic() - t0
    rec["cpu_s"] = time.process_time() - c0  # the worker process's CPU time (all its threads) on this bag
    rec["peak_rss_mb"] = _peak_rss_mb()
    return rec


# ---------------------------------------------------------------------------------------------------- dask
@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None,
                threads_per_worker: int = 1) -> Iterator[Any]:
    """A ``distributed.Client``: connected to ``scheduler`` (``tcp://host:port``) when given, else to a new local
    cluster of ``workers`` worker processes (default: one per core) on the loopback interface, closed on exit."""
    import logging

    try:
        from distributed import Client, LocalCluster
    except ImportError as e:  # the [fleet] extra: the node and the single-process tools do not need Dask
        raise SystemExit(f"Dask is not installed ({e}): pip install 'xmetro_ros[fleet]'") from e

    if scheduler:
        with Client(scheduler) as client:
            yield client
        return
    n = int(workers or os.cpu_count() or 1)
    # Every listening socket (scheduler, nannies, workers, dashboard) on the loopback interface.
    with LocalCluster(n_workers=n, threads_per_worker=threads_per_worker, processes=True, host="127.0.0.1",
                      dashboard_address="127.0.0.1:0", silence_logs=logging.ERROR) as cluster, \
            Client(cluster) as client:
        yield client


def run_fleet(jobs: list[BagJob], client: Any, out_dir: str | Path, *, model_dir: str | None = None,
              params: dict[str, Any] | None = None, topics: list[str] | None = None, deterministic: bool = False,
              redo: bool = False, log: Callable[[str], None] | None = None) -> FleetResult:
    """Submit one :func:`predict_job` per bag not yet done (all with ``redo``) to ``client``, collect the records
    as they complete (one progress line each through ``log``), then write the summary, overview and status.
    A worker lost during a task fails that bag only."""
    from distributed import as_completed

    t0 = time.monotonic()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    res = FleetResult(workers=len(client.scheduler_info().get("workers", {})))
    todo = []
    for j in jobs:
        if not redo and j.done():
            rec = {"bag": j.bag, "name": j.name, "cell": j.cell, "out": j.out, "status": "skipped",
                   "scans": count_rows(j.scans)}
            damage = damage_record(j.out)
            if damage.is_file():  # the run that judged it found the input damaged: still true, still reported
                with contextlib.suppress(OSError, ValueError):
                    rec["losses"] = json.loads(damage.read_text()).get("losses", [])
                    rec["damaged"] = True
            res.bags.append(rec)
        else:
            todo.append(j)
    if log and len(todo) < len(jobs):
        log(f"{len(jobs) - len(todo)} bag(s) already done: skipped")
    futures = {client.submit(predict_job, j, model_dir, params, topics, deterministic, pure=False,
                             key=f"xmetro-predict-{i}-{j.name}"): j for i, j in enumerate(todo)}
    for k, fut in enumerate(as_completed(futures), 1):
        j = futures[fut]
        try:
            rec = fut.result()
        except Exception as e:  # the task itself died (worker killed, unpicklable result)
            rec = {"bag": j.bag, "name": j.name, "cell": j.cell, "out": j.out, "status": "failed", "scans": 0,
                   "error": f"{type(e).__name__}: {e}"}
        res.bags.append(rec)
        if log:
            what = rec.get("error") if rec["status"] == "failed" else f"{rec['scans']} scans"
            log(f"[{k}/{len(todo)}] {rec['status']:<7s} {j.name}: {what} ({rec.get('wall_s', 0):.1f} s)")
    order = {j.name: i for i, j in enumerate(jobs)}
    res.bags.sort(key=lambda b: order[b["name"]])
    res.summary = write_summary(jobs, out_dir / SUMMARY)
    if res.summary is not None:
        res.overview = write_overview(res.summary, out_dir / OVERVIEW, res.bags)
    res.wall_s = time.monotonic() - t0
    (out_dir / STATUS).write_text(json.dumps({"workers": res.workers, "wall_s": res.wall_s, "bags": res.bags},
                                             indent=1, default=str))
    return res


# ---------------------------------------------------------------------------------------------------- CLI
def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``xmetro fleet`` (sub-command ``predict``) to the ``xmetro`` sub-commands."""
    p = subparsers.add_parser("fleet", help="re-judge many bags on Dask (local processes or a cluster)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="fleet_command", metavar="FLEET_COMMAND")
    q = sub.add_parser("predict", help="judge every scan of many bags as the live node would",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    q.add_argument("inputs", nargs="+", help=".mcap files, rosbag2 directories, directories of them, globs")
    q.add_argument("--out-dir", required=True, help="output directory (bags, summary.parquet, overview.html)")
    q.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                   help="an existing Dask scheduler (default: a local cluster of worker processes)")
    q.add_argument("--workers", type=int, default=None, help="local cluster: worker processes (default: cores)")
    q.add_argument("--cell", action="append", default=[], metavar="PATTERN=NAME",
                   help="cell of the bags whose path matches the glob PATTERN (repeatable; default: the bag's "
                        "directory name)")
    q.add_argument("--model", default=None, metavar="DIR", help="model directory (default: the shipped model)")
    q.add_argument("--topic", action="append", help="PointCloud2 topic to judge (repeatable; default: all inputs)")
    q.add_argument("--param", action="append", metavar="NAME=VALUE", help="node parameter override (repeatable)")
    q.add_argument("--deterministic", action="store_true",
                   help="write processing_latency = 0 so outputs are identical byte for byte run after run")
    q.add_argument("--redo", action="store_true", help="recompute bags whose outputs exist")
    q.add_argument("--allow-partial", action="store_true",
                   help="exit 0 when bags lost data but what they held was judged (default: exit 1, as xmetro predict)")
    q.set_defaults(func=run)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def _parse_cells(items: list[str]) -> list[tuple[str, str]]:
    out = []
    for it in items:
        pattern, sep, name = it.rpartition("=")
        if not sep or not pattern or not name:
            raise ValueError(f"--cell expects PATTERN=NAME, got {it!r}")
        out.append((pattern, name))
    return out


def run(args: argparse.Namespace) -> int:
    """``xmetro fleet predict``: exit 0 when every bag is done (or skipped), 1 when any failed or lost data (lost
    data in this run or a run before it; ``--allow-partial`` accepts it)."""
    from .predict import PredictError, _parse_params, node_values

    try:
        # one thread per worker process unless asked otherwise: a worker per core, no oversubscription
        params = {"threads": 1, **_parse_params(args.param)}
        node_values(args.model, params)  # refuse bad parameters before starting a cluster
        jobs = plan_jobs(find_bags(args.inputs), args.out_dir, _parse_cells(args.cell))
    except (PredictError, ValueError, FileNotFoundError) as e:
        print(f"xmetro fleet predict: error: {e}", file=sys.stderr)
        return 2
    model = str(Path(args.model).resolve()) if args.model else None
    print(f"{len(jobs)} bag(s) → {args.out_dir} on " + (args.scheduler or f"a local cluster of "
          f"{args.workers or os.cpu_count()} worker process(es)"), file=sys.stderr)
    with dask_client(args.scheduler, args.workers) as client:
        res = run_fleet(jobs, client, args.out_dir, model_dir=model, params=params, topics=args.topic,
                        deterministic=args.deterministic, redo=args.redo,
                        log=lambda s: print(s, file=sys.stderr, flush=True))
    for b in res.bags:
        if b["status"] in ("failed", "damaged") or b.get("damaged"):
            what = "DAMAGED (an earlier run)" if b["status"] == "skipped" else b["status"].upper()
            print(f"{what}: {b['bag']}: {b.get('error') or '; '.join(b.get('losses') or [])}", file=sys.stderr)
    print(f"fleet: {res.count('done')} done, {res.count('skipped')} skipped, {res.count('damaged')} damaged, "
          f"{res.count('failed')} failed; {res.scans} scans in {res.wall_s:.1f} s on {res.workers} worker(s); "
          f"summary {res.summary}, overview {res.overview}")
    return 1 if res.count("failed") or (res.lost_data and not args.allow_partial) else 0

