"""The learning table of :func:`xmetro_ros.dataset.build_table`, built with the scans spread over Dask workers.

The same table, array for array: the per-scan work is the same functions (``prepare_scan``,
:func:`~xmetro_ros.dataset.scan_part`) and the one thing that couples the scans — the seeded sampling of at most
``max_points_per_cloud`` rows per scan, drawn from one generator over the scans in order — is done on the client
between two rounds of tasks, from the scans' sizes alone:

1. per source (a picklable callable returning a list of scans, e.g. simulating a few campaign items or reading one
   bag), a task loads and prepares its scans (decode → outlier removal, normals) and keeps them on its worker;
   only their point counts come back;
2. the client draws each scan's rows (:func:`~xmetro_ros.dataset.sample_rows`, in scan order, as build_table);
3. per source, a task on the worker holding its prepared scans computes features, targets and oracle of the drawn
   rows; the parts come back in source order and are concatenated (:func:`~xmetro_ros.dataset.assemble_table`).

Memory: each worker holds the prepared scans of its sources between rounds 1 and 3 (the campaign is spread over
the cluster, not held by one process); the client holds only the table.

:func:`load_inputs_dask` does the same for the inputs of ``xmetro loop`` (``loop.inputs.load_inputs``): one task
per input (a bag streamed scan by scan, a NIST set, an AT C5 directory) runs ``loop.inputs.load_path`` on a worker;
the client concatenates the tables in input order — the very table of the single-process path.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .dataset import DatasetError, Table, TablePart, assemble_table, sample_rows, scan_part
from .preprocess import PreprocessConfig, prepare_scan
from .scan import Scan
from .scanner import ScannerModel

if TYPE_CHECKING:
    from .loop.data import LoopData

__all__ = ["ScanList", "SimulateItems", "build_table_dask", "load_inputs_dask"]

Source = Callable[[], list[Scan]]


class ScanList:
    """A source of scans already in memory (shipped to the worker with the task)."""

    def __init__(self, scans: Sequence[Scan]) -> None:
        self.scans = list(scans)

    def __call__(self) -> list[Scan]:
        return self.scans


class SimulateItems:
    """A source that simulates campaign items (``item.simulate()``) on the worker."""

    def __init__(self, items: Sequence[Any]) -> None:
        self.items = list(items)

    def __call__(self) -> list[Scan]:
        return [it.simulate() for it in self.items]


def _prepare(source: Source, cfg: PreprocessConfig, scanner: ScannerModel | None) -> list[tuple[Scan, Any]]:
    scanner = scanner or ScannerModel.load()
    out = []
    for j, scan in enumerate(source()):
        if scan.artifact is None:
            raise DatasetError(f"scan {j} of source {source!r} has no artifact: targets need the nominal shape")
        out.append((scan, prepare_scan(scan, cfg, scanner=scanner)))
    return out


def _sizes(prepared: list[tuple[Scan, Any]]) -> list[int]:
    return [len(p) for _, p in prepared]


def _parts(prepared: list[tuple[Scan, Any]], sels: list[np.ndarray | None], names: list[str],
           fit_center: bool) -> list[TablePart]:
    return [scan_part(s, p, sel, names, fit_center) for (s, p), sel in zip(prepared, sels, strict=True)]


def build_table_dask(sources: Sequence[Source], feature_names: Sequence[str], client: Any,
                     preprocess_cfg: PreprocessConfig | None = None, *, max_points_per_cloud: int | None = 2000,
                     seed: int = 0, fit_center: bool = False, scanner: ScannerModel | None = None,
                     progress: Callable[[str], None] | None = None) -> Table:
    """The table ``build_table(scans)`` returns, where ``scans`` is the concatenation of the sources' scans in
    order, computed on the workers of ``client`` (a ``distributed.Client``). Arguments as build_table's.

    Raises:
        DatasetError: no feature names, no scans, a scan without artifact (from the worker).
    """
    from distributed import wait

    names = list(feature_names)
    if not names:
        raise DatasetError("no feature names")
    cfg = preprocess_cfg or PreprocessConfig()
    prepared = [client.submit(_prepare, s, cfg, scanner, pure=False) for s in sources]
    sizes = client.gather([client.submit(_sizes, f) for f in prepared])
    if progress:
        progress(f"prepared {sum(map(len, sizes))} scans from {len(sources)} source(s) on the workers")
    rng = np.random.default_rng(seed)  # the draws of build_table, in scan order, from the sizes alone
    sels = [[sample_rows(rng, n, max_points_per_cloud) for n in ns] for ns in sizes]
    parts = [client.submit(_parts, f, sel, names, fit_center, pure=False) for f, sel in zip(prepared, sels,
                                                                                           strict=True)]
    wait(parts)
    table_parts = [p for ps in client.gather(parts) for p in ps]
    del prepared  # release the prepared scans held by the workers
    if not table_parts:
        raise DatasetError("no scans")
    return assemble_table(table_parts, names)


def load_inputs_dask(paths: Sequence[str | Path], artifact_spec: str | None, feature_names: list[str] | None,
                     client: Any, read_bag: Callable[[Path], Iterable[Scan]] | None = None,
                     progress: Callable[[str], None] | None = None) -> LoopData:
    """The table ``loop.inputs.load_inputs(paths, artifact_spec, feature_names, read_bag)`` returns, each input
    read, pre-processed, and turned into features and targets on a worker of ``client`` (``loop.inputs.load_path``;
    ``read_bag`` must be importable on the workers, e.g. ``xmetro_ros.ros.scan_io.iter_scans``, which streams a bag
    scan by scan). Paths are made absolute (the workers read them: a shared file system on several machines). One
    progress line per input as it completes; every input is tried, then the first failure in input order is
    raised (the error the single-process path raises).

    Raises:
        LoopInputError (or the reader's ValueError): as ``load_inputs``.
    """
    from distributed import as_completed

    from .loop.data import LoopData
    from .loop.inputs import check_inputs, load_path

    feats = list(feature_names) if feature_names is not None else None
    kind, art, fit = check_inputs(list(paths), artifact_spec, feats)
    futures = {client.submit(load_path, str(Path(p).resolve()), kind, art, fit, feats, read_bag, pure=False): i
               for i, p in enumerate(paths)}
    results: list[Any] = [None] * len(paths)
    for k, fut in enumerate(as_completed(futures), 1):
        i = futures[fut]
        try:
            results[i] = fut.result()  # gathered as it completes: the worker releases it
            what = f"{len(results[i].groups)} group(s), {results[i].n} points"
        except Exception as e:  # raised below, in input order
            results[i] = e
            what = f"failed: {type(e).__name__}: {e}"
        if progress:
            progress(f"[{k}/{len(paths)}] {paths[i]}: {what}")
    del futures
    for r in results:
        if isinstance(r, BaseException):
            raise r
    return LoopData.concat(results)
