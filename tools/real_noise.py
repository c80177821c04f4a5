"""The measured noise (preprocess/noise.py) on a real profilometer, against the data's own random error:
``python tools/real_noise.py [DATA_DIR]`` (default ../shared/data/measured/profiler_sphere_r19_labelled, its
training list).

Each profile's arc points (the product's own segmentation, calibrate/profile_table.py) are laid on a one-row grid
in x order and measured by the product's kernel (``grid_noise_scale``: second differences along the line projected
on the arc's normal; a 1 × 15 window, as a single profile has no neighbouring rows). The repeats of a position (the
sensor not moved between them) give each point's random error as their spread. Printed: both scales over the
points with ≥ 3 repeats, and the ratio of their medians per profile. Quoted in docs/real-data.md.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from xmetro_ros.calibrate.profile_table import build_profile_table
from xmetro_ros.preprocess.noise import grid_noise_scale
from xmetro_ros.scan.profiles import load_profile_list

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT.parent / "shared" / "data" / "measured" / "profiler_sphere_r19_labelled"
R19_RADIUS_MM = 19.05
WINDOW = 15  # one row: 15 columns, at most 15 second differences (the 7 × 7 window's minimum is 10)


def main(data: Path = DEFAULT) -> None:
    t = build_profile_table(load_profile_list(data / "train_file.txt"), R19_RADIUS_MM, seed=0)
    scale = np.full(len(t.profile), np.nan)
    for k in np.unique(t.profile):
        rows = np.flatnonzero((t.profile == k) & t.kept)
        rows = rows[np.argsort(t.xz[rows, 0], kind="stable")]
        if len(rows) < 3:
            continue
        pts = np.column_stack([t.xz[rows, 0], np.zeros(len(rows)), t.xz[rows, 1]])
        nrm = np.column_stack([t.normals[rows, 0], np.zeros(len(rows)), t.normals[rows, 1]]).astype(np.float32)
        scale[rows] = grid_noise_scale(pts, nrm, np.arange(len(rows)), (1, len(rows)), window=WINDOW)
    m = t.kept & np.isfinite(scale) & np.isfinite(t.spread) & (t.n_repeats >= 3)
    print(f"{data.name}, training list: {int(m.sum())} arc points with >= 3 repeats, "
          f"{len(np.unique(t.profile[m]))} profiles")
    for label, v in (("measured noise (second differences)", scale[m]), ("repeat spread (random error)", t.spread[m])):
        print(f"  {label:36s} median {1e3 * np.median(v):5.2f} um, RMS {1e3 * np.sqrt(np.mean(v ** 2)):5.2f} um")
    ratio = [np.median(scale[m & (t.profile == k)]) / np.median(t.spread[m & (t.profile == k)])
             for k in np.unique(t.profile[m])]
    q = np.quantile(ratio, [0.1, 0.5, 0.9])
    print(f"  per profile, median measured / median spread: q10 {q[0]:.2f}, median {q[1]:.2f}, q90 {q[2]:.2f}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT)
