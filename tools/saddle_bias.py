"""Where the saddle's X intervals fail, and why: ``python tools/saddle_bias.py [MODEL_DIR]``.

The test part ``saddle`` (z = 4 + x²/90 − y²/50 mm, presented as in the parts study) scanned at 10/4/0.5, seed 1,
judged by the node's path (``ScanHandler.process``). Per band of x (mm, scan frame) the coverage of
|actual − d| ≤ U on X, the simulator's mean systematic X error (``expected_error``), the model's mean X prediction
and their difference (the model's bias), and the share of the band flagged out of domain; then the same per |N_x|
with the median U_x, the 95 % quantile of |actual − d| on X, the noise's own X spread (actual − expected) and the
measured noise along the normal times |N_x| (what U takes under σ̂). µm. Its figures are quoted in
docs/parts-generalisation.md (issue 28: the saddle's X).
"""

from __future__ import annotations

import sys

import numpy as np

from xmetro_ros.judge import flags as fl
from xmetro_ros.judge.inference import ModelSet
from xmetro_ros.judge.scan_handler import ScanHandler
from xmetro_ros.parts.study import PRESENTATION
from xmetro_ros.scan.generated_parts import make_part
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim import simulate_scan


def main(model_dir: str | None = None) -> None:
    sc = ScannerModel.load()
    ms = ModelSet.load(model_dir) if model_dir else ModelSet.load()
    h = ScanHandler(ms, sc)
    man = make_part("saddle", form_um=40.0).transformed(PRESENTATION)
    scan = simulate_scan(man, ScanSettings(10.0, 4.0, 0.5), scanner=sc, seed=1)
    res = h.process(scan)
    idx = np.asarray(res.prepared.index)
    pts = np.asarray(res.scan.points, np.float64).reshape(-1, 3)[idx]
    inj = (np.zeros(len(idx), bool) if scan.injected_outlier is None
           else np.asarray(scan.injected_outlier).reshape(-1)[idx])
    pred, u = res.predictions, res.row_uncertainty
    assert u is not None and res.noise is not None
    use = np.isfinite(pred).all(axis=1) & np.isfinite(u).all(axis=1) & ~inj
    pts, pred, u, noise = pts[use], pred[use], u[use], res.noise[use]
    ood = (res.flags[idx][use] & fl.FLAG_OUT_OF_DOMAIN) != 0
    actual = man.errors(pts)
    expected = np.asarray(scan.expected_error).reshape(-1, 3)[idx][use]
    r = actual - pred
    cov = np.abs(r[:, 0]) <= u[:, 0]
    print(f"model {ms.id} ({model_dir or 'shipped'}); saddle, 10/4/0.5, seed 1: {len(pts)} points, X covered "
          f"{100 * cov.mean():.1f} %")
    print("x band (mm)    points  X covered  systematic X  predicted X  bias  out of domain")
    x = pts[:, 0]
    for lo in range(-24, 24, 8):
        m = (x >= lo) & (x < lo + 8)
        if m.sum() < 50:
            continue
        ex, px = 1e3 * expected[m, 0].mean(), 1e3 * pred[m, 0].mean()
        print(f"{lo:4d} .. {lo + 8:4d}  {m.sum():7d}  {100 * cov[m].mean():8.1f} %  {ex:11.2f}  {px:11.2f}  "
              f"{px - ex:5.2f}  {100 * ood[m].mean():12.1f} %")
    nx = np.abs(man.normals(pts)[:, 0])
    print("|N_x|       points  X covered  median U_x  p95 |actual - d|  noise X s.d.  measured noise |N_x|")
    for lo, hi in ((0.0, 0.1), (0.1, 0.2), (0.2, 0.3), (0.3, 0.4), (0.4, 0.6)):
        m = (nx >= lo) & (nx < hi)
        if m.sum() < 50:
            continue
        print(f"{lo:.1f} .. {hi:.1f}  {m.sum():7d}  {100 * cov[m].mean():8.1f} %  {1e3 * np.median(u[m, 0]):10.2f}  "
              f"{1e3 * np.percentile(np.abs(r[m, 0]), 95):16.2f}  {1e3 * np.std(actual[m, 0] - expected[m, 0]):12.2f}  "
              f"{1e3 * np.nanmedian(noise[m] * nx[m]):20.2f}")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else None)
