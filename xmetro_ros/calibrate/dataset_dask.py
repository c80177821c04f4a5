"""The learning table of :func:`xmetro_ros.calibrate.dataset.build_table`, built with the scans spread over Dask
workers.

The same table, array for array: the per-scan work is the same functions (``prepare_scan``,
:func:`~xmetro_ros.calibrate.dataset.scan_part`) and the one thing that couples the scans — the seeded sampling of at
most
``max_points_per_cloud`` rows per scan, drawn from one generator over the scans in order — is done on the client
between two rounds of tasks, from the scans' sizes alone:

1. per source (a picklable callable returning a list of scans, e.g. simulating a few campaign items or reading one
   bag), a task loads and prepares its scans (decode → outlier removal, normals) and keeps them on its worker;
   only their point counts come back;
2. the client draws each scan's rows (:func:`~xmetro_ros.calibrate.dataset.sample_rows`, in scan order, as build_table);
3. per source, a task on the worker holding its prepared scans computes features, targets and oracle of the drawn
   rows; the parts come back in source order and are concatenated
   (:func:`~xmetro_ros.calibrate.dataset.assemble_table`).

Memory: each worker holds the prepared scans of its sources between rounds 1 and 3 (the campaign is spread over
the cluster, not held by one process); the client holds only the table.

The loop's inputs on Dask are :mod:`xmetro_ros.loop.inputs_dask`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ..preprocess import PreprocessConfig, prepare_scan
from ..scan.scan import Scan
from ..scan.scanner import ScannerModel
from .dataset import DatasetError, Table, TablePart, assemble_table, sample_rows, scan_part

__all__ = ["ScanList", "SimulateItems", "build_table_dask"]

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
