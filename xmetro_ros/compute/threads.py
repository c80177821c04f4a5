"""One thread budget for the judge: numba's parallel kernels, the model set's ONNX runs and the numpy row blocks
(:func:`parallel_for`) share it.

The judge's stages run one after the other (pre-processing and features, then the ONNX runs, then flags and
outputs), so they can all use the same ``n`` threads without oversubscribing the machine. The
node's parameter ``threads`` sets it; 0 (the default) means :func:`default_threads`: the CPUs this process may run
on (its affinity mask, which a container's or ``taskset``'s limit sets) less one, at least 1, at most
:data:`MAX_DEFAULT_THREADS`. Why one less: a parallel kernel waits for its slowest thread, and a thread that shares
its core with the driver, DDS or the node's executor stalls all of them. On the 2-core machine with two other busy
processes the organized judge took 157-160 ms at 2 threads and 114-138 ms at 1 (bench/bench_threads.py, two runs),
so a 2-core machine judges on 1.

numba's thread count is per calling thread (``numba.set_num_threads``), so whatever thread judges calls
:func:`use_threads` first (``ScanHandler.process`` does). The threading layer is numba's "threadsafe" choice (TBB,
else OpenMP): the node's worker and its service threads may launch kernels at the same time, which numba's own
"workqueue" layer does not allow (it aborts the process). A ``NUMBA_THREADING_LAYER`` set in the environment wins.

Results do not depend on the thread count: every parallel kernel splits its loop over rows or points and each
iteration writes only its own outputs, in the serial code's float operations (test/test_compute_threads.py).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

# numba's OpenMP workers sleep when a parallel kernel ends instead of spinning for a while: the judge's stages
# between kernels (ONNX runs, numpy blocks on helper threads) need those cores at once. On the 2-core machine the
# organized judge at 2 threads took 70-76 ms with sleeping workers and 102-106 ms with spinning ones (1 thread:
# 98-100 ms either way; bench/bench_scaling.py). Read by OpenMP when numba's layer starts, i.e. at the first
# parallel kernel, after this import; a value set in the environment wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numba
from numba.core import config as _numba_config

__all__ = ["MAX_DEFAULT_THREADS", "NUMPY_BLOCK_THREADS", "available_cpus", "block_bounds", "budget", "default_threads",
           "max_threads", "parallel_for", "resolve_threads", "row_blocks", "use_threads"]

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


def budget() -> int:
    """The calling thread's thread budget: numba's count for it (:func:`use_threads` sets it; the judge calls it
    first)."""
    return int(numba.get_num_threads())


_POOL: list[ThreadPoolExecutor] = []
_POOL_LOCK = threading.Lock()
_POOL_PREFIX = "xmetro-compute"


def _pool() -> ThreadPoolExecutor:
    """The process's helper threads for :func:`parallel_for`, made at first use (twice numba's pool: two judges,
    the node's worker and a service, may run side by side)."""
    with _POOL_LOCK:
        if not _POOL:
            _POOL.append(ThreadPoolExecutor(max(2, 2 * max_threads()), thread_name_prefix=_POOL_PREFIX))
        return _POOL[0]


def parallel_for(fn: Callable[[int], None], n: int, threads: int) -> None:
    """``fn(i)`` for every ``i`` in ``range(n)``, on up to ``threads`` threads: the caller and helpers from a shared
    pool, each taking the next ``i`` when it is done with one (load balance). Returns when every call has returned;
    the first exception raised by a call is raised again here (the other calls still run).

    For work that releases the GIL (ONNX Runtime runs, numpy on large blocks): each ``i`` must write only its own
    outputs, so the result does not depend on ``threads``. Called from a helper thread (nested), or with one
    thread or one item, it runs in the caller alone."""
    threads = min(int(threads), n)
    if threads <= 1 or threading.current_thread().name.startswith(_POOL_PREFIX):
        for i in range(n):
            fn(i)
        return
    it = iter(range(n))
    lock = threading.Lock()
    done = threading.Event()
    state = {"finished": 0}
    errors: list[BaseException] = []

    def work() -> None:
        while True:
            with lock:
                i = next(it, None)
            if i is None:
                return
            try:
                fn(i)
            except BaseException as e:  # re-raised in the caller
                errors.append(e)
            with lock:
                state["finished"] += 1
                if state["finished"] == n:
                    done.set()

    pool = _pool()
    for _ in range(threads - 1):
        pool.submit(work)
    work()  # the caller takes items too: it never waits on a helper that has not started
    done.wait()
    if errors:
        raise errors[0]


#: Threads at most for numpy work split into row blocks (the features): each block is many small numpy
#: operations, each taking the GIL, and beyond 4 threads the blocks wait on it more than they gain (16 cores: the
#: features took 5.3 ms at 4 threads, 6.6 at 8, 13.5 at 16; bench/results/scaling_16core.json).
NUMPY_BLOCK_THREADS = 4


def block_bounds(n: int, threads: int, min_block: int, per_thread: int = 1) -> list[tuple[int, int]]:
    """Row ranges ``[lo, hi)`` covering ``range(n)`` for :func:`parallel_for`: ``per_thread`` per thread (more
    balance the load when a thread can be held up; fewer cost fewer hand-offs), none smaller than ``min_block``
    rows, at least one; one with one thread."""
    if threads <= 1:
        return [(0, n)]
    k = max(1, min(per_thread * threads, n // max(1, min_block)))
    return [(i * n // k, (i + 1) * n // k) for i in range(k)]
