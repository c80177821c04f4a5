"""`make bench`: run every benchmark (bench/bench_*.py: node, dds, bag, preprocess, replay, soak) one after the other;
each writes bench/results/<name>.json (bench_soak.py: the node's memory soak, ~3 min).

Benchmarks measure side by side in one run and report ratios, since this machine is noisy; they are never tests.
Pass names to run a subset: `python bench/run_all.py node dds`.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

from xmetro_ros.ros.dds_env import ros_env

HERE = Path(__file__).resolve().parent


def main(argv: list[str]) -> int:
    scripts = sorted(HERE.glob("bench_*.py"))
    if argv:
        scripts = [s for s in scripts if s.stem.removeprefix("bench_") in argv]
    failed = []
    for script in scripts:
        t0 = time.monotonic()
        print(f"== {script.name}", flush=True)
        rc = subprocess.call([sys.executable, str(script)], env=ros_env(), cwd=HERE.parent)
        print(f"== {script.name}: exit {rc} in {time.monotonic() - t0:.0f} s", flush=True)
        if rc:
            failed.append(script.name)
    if failed:
        print(f"bench: failed: {', '.join(failed)}")
        return 1
    print(f"bench: results in {HERE / 'results'}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
