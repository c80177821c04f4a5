"""glibc's allocator tuned for scan after scan (xmetro_ros/compute/malloc.py, applied by xmetro_node at start): what
it sets, that the environment's own settings win, and what it buys, each in a fresh process (the test process's
allocator stays as it is): a round of ten 4 MB arrays (a scan's arrays are a few MB each) freed and allocated again
maps fresh zero-filled pages each round with glibc's defaults (its threshold follows the freed blocks, but the
heap's free top is trimmed past twice that), and reuses the heap's pages once tuned."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys

import pytest

from xmetro_ros.compute import malloc

pytestmark = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="the tuning is glibc's mallopt")

_SCRIPT = """
import json, resource, sys
import numpy as np
from xmetro_ros.compute.malloc import tune_for_scans
done = tune_for_scans() if sys.argv[1] == "tuned" else {}
def scan_round():
    arrays = [np.ones(500_000) for _ in range(10)]  # 4 MB each, written
    del arrays
scan_round(); scan_round()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
scan_round()
print(json.dumps({"set": done, "faults": resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before}))
"""


def _run(mode: str, **env: str) -> dict:
    clean = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"}
    out = subprocess.run([sys.executable, "-c", _SCRIPT, mode], env={**clean, **env}, capture_output=True, text=True,
                         timeout=120, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])



def test_tuned_rounds_reuse_the_heap_where_the_defaults_map_fresh_pages() -> None:
    default, tuned = _run("default"), _run("tuned")
    assert tuned["set"] == {"arena_max": malloc.ARENAS, "mmap_threshold": malloc.MMAP_THRESHOLD,
                            "trim_threshold": malloc.TRIM_THRESHOLD}
    # 40 MB in 4 KiB pages: ~9,800 faults when every page is fresh (9,734 here)
    assert default["faults"] > 3000, default
    assert tuned["faults"] < 300, tuned


def test_the_environments_settings_win() -> None:
    r = _run("tuned", MALLOC_MMAP_THRESHOLD_="131072", MALLOC_ARENA_MAX="4")
    assert r["set"] == {"arena_max": 4, "trim_threshold": malloc.TRIM_THRESHOLD}
    r = _run("tuned", GLIBC_TUNABLES="glibc.malloc.trim_threshold=65536:glibc.malloc.arena_max=1")
    assert r["set"] == {"mmap_threshold": malloc.MMAP_THRESHOLD}
    r = _run("tuned", MALLOC_ARENA_MAX="many")
    assert "arena_max" not in r["set"] and "mmap_threshold" in r["set"]


def test_without_mallopt_nothing_is_set(monkeypatch: pytest.MonkeyPatch) -> None:
    """A C library without ``mallopt`` (not glibc): nothing is changed, nothing raised."""
    def no_libc(_name: str) -> None:
        raise OSError("no libc.so.6")

    monkeypatch.setattr(malloc.ctypes, "CDLL", no_libc)
    assert malloc.tune_for_scans({}) == {}
