"""One thread budget for the judge: numba's parallel kernels and ONNX Runtime's intra-op threads share it.

The judge's stages run one after the other (pre-processing and features in compiled kernels, then the ONNX call,
then flags and outputs), so both libraries can use the same ``n`` threads without oversubscribing the machine. The
node's parameter ``threads`` sets it; 0 (the default) means :func:`default_threads`: the CPUs this process may run
on (its affinity mask, which a container's or ``taskset``'s limit sets) less one, at least 1, at most
:data:`MAX_DEFAULT_THREADS`. Why one less: a parallel kernel waits for its slowest thread, and a thread that shares
its core with the driver, DDS or the node's executor stalls all of them. On the 2-core machine with two other busy
processes the organized judge took 360-409 ms at 2 threads and 148-224 ms at 1 (quiet: 117 vs 120 ms,
bench/bench_threads.py), so a 2-core machine judges on 1.

numba's thread count is per calling thread (``numba.set_num_threads``), so whatever thread judges calls
:func:`use_threads` first (``ScanHandler.process`` does). The threading layer is numba's "threadsafe" choice (TBB,
else OpenMP): the node's worker and its service threads may launch kernels at the same time, which numba's own
"workqueue" layer does not allow (it aborts the process). A ``NUMBA_THREADING_LAYER`` set in the environment wins.

Results do not depend on the thread count: every parallel kernel splits its loop over rows or points and each
iteration writes only its own outputs, in the serial code's float operations (test/test_compute_threads.py).
"""

from __future__ import annotations

import os

import numba
from numba.core import config as _numba_config

__all__ = ["MAX_DEFAULT_THREADS", "available_cpus", "default_threads", "max_threads", "resolve_threads", "row_blocks",
           "use_threads"]

#: The default budget's cap: beyond it the judge's stages stop gaining (docs/performance.md) and a shared cell PC
#: keeps cores for its driver and DDS.
MAX_DEFAULT_THREADS = 16

if not os.environ.get("NUMBA_THREADING_LAYER"):
    # before any parallel kernel runs (the layer is chosen at the first launch)
    _numba_config.THREADING_LAYER = "threadsafe"  # type: ignore[attr-defined]



@numba.njit(cache=True, nogil=True)
def row_blocks(n: int, threads: int) -> int:  # pragma: no cover - compiled
    """Blocks to split ``n`` rows into for a parallel driver run on ``threads`` threads (the caller's
    ``numba.get_num_threads()``, passed in: a kernel that asks numba itself cannot be cached): 4 per thread (load
    balance), at most ``n``, at least 1. Which rows a block gets never changes a result (each row is written by one
    block)."""
    return max(1, min(n, 4 * threads))


def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask; ``os.cpu_count()`` where the platform has none)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def max_threads() -> int:
    """numba's pool size (``NUMBA_NUM_THREADS``, the machine's CPUs unless set): no budget can exceed it."""
    return int(_numba_config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]


def default_threads() -> int:
    """The budget of ``threads: 0``: :func:`available_cpus` less one (the driver's, DDS's and the executor's), at
    least 1, at most :data:`MAX_DEFAULT_THREADS`."""
    return max(1, min(available_cpus() - 1, MAX_DEFAULT_THREADS, max_threads()))


def resolve_threads(requested: int) -> int:
    """Threads for a requested budget: 0 → :func:`default_threads`; else ``requested`` clipped to numba's pool."""
    n = int(requested)
    if n < 0:
        raise ValueError(f"threads must be >= 0 (0: automatic), got {n}")
    return default_threads() if n == 0 else max(1, min(n, max_threads()))


def use_threads(n: int) -> None:
    """numba's parallel kernels launched from the calling thread use ``n`` threads (resolved: 0 = automatic)."""
    numba.set_num_threads(resolve_threads(n))
