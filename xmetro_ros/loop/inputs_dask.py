"""The inputs of ``xmetro loop`` read on Dask workers: one task per input (a bag streamed scan by scan, a NIST set, an
AT C5 directory) runs :func:`~xmetro_ros.loop.inputs.load_path` on a worker; the client concatenates the tables in
input order — the very table of the single-process path (``loop.inputs.load_inputs``). Lengths in mm.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

from ..scan.scan import Scan
from .data import LoopData
from .inputs import check_inputs, load_path

__all__ = ["load_inputs_dask"]


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
