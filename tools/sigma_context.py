"""How σ̂ of a flat point depends on the shapes scanned with it: ``python tools/sigma_context.py MODEL_DIR``.

A flat patch seen within 20° of normal incidence at 6/3/0.1 carries the same noise on every part (the simulator's
std, ~16.4 µm along Z); the PointNet's σ̂ of such points is printed next to it for a plain plate, a plate with a
groove, and the test parts ``bowl`` and ``step``, with the scan's measured noise along Z (preprocess/noise.py:
s·|N_z|, what a card with ``by_surface.noise`` puts under σ̂), the 95 % quantile of |actual − d| and the mean U_z.
Its figures are quoted in docs/parts-generalisation.md ("σ̂ moves with the part").
"""

from __future__ import annotations

import sys

import numpy as np

from xmetro_ros.judge.inference import ModelSet
from xmetro_ros.judge.scan_handler import ScanHandler
from xmetro_ros.judge.surface_class import SURFACE_CLASSES, surface_class
from xmetro_ros.parts.study import PRESENTATION
from xmetro_ros.preprocess.curvature import principal_curvatures
from xmetro_ros.preprocess.noise import noise_scale
from xmetro_ros.scan.calibration_surfaces import make_surface, surface_presentation
from xmetro_ros.scan.generated_parts import make_part
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim import simulate_scan


def main(model_dir: str | None = None) -> None:
    sc = ScannerModel.load()
    ms = ModelSet.load(model_dir) if model_dir else ModelSet.load()
    h = ScanHandler(ms, sc)
    st = ScanSettings(6.0, 3.0, 0.1)
    cases = (("plate", make_surface("plate").transformed(surface_presentation((0.0, 0.0)))),
             ("groove", make_surface("groove").transformed(surface_presentation((0.0, 0.0)))),
             ("bowl", make_part("bowl", 40.0).transformed(PRESENTATION)),
             ("step", make_part("step", 40.0).transformed(PRESENTATION)))
    print(f"model {ms.id} ({model_dir or 'shipped'}); flat points within 20 deg of normal incidence, 6/3/0.1, seed 5")
    for label, art in cases:
        scan = simulate_scan(art, st, scanner=sc, seed=5)
        r = h.process(scan)
        idx = np.asarray(r.prepared.index)
        cls = surface_class(principal_curvatures(r.prepared))
        _, sig = ms.predict_with_sigma(r.features)
        std = np.asarray(scan.noise_std).reshape(-1, 3)[idx]
        n = np.asarray(r.prepared.normals, np.float64)
        inc = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n, np.asarray(r.prepared.geometry.L)), -1, 1)))
        m = (cls == SURFACE_CLASSES.index("flat")) & (inc < 20) & np.isfinite(sig[:, 2]) & np.isfinite(std[:, 2])
        meas = noise_scale(r.prepared) * np.abs(n[:, 2])
        res = np.abs(art.errors(np.asarray(r.prepared.points)) - r.deviations[idx])[m, 2]
        u_z = r.uncertainty[idx][m, 2].mean()
        print(f"  {label:7s} n {int(m.sum()):6d}  sigma_hat_z {1e3 * sig[m, 2].mean():5.2f} um  true std_z "
              f"{1e3 * std[m, 2].mean():5.2f} um  ratio {sig[m, 2].mean() / std[m, 2].mean():.2f}  measured "
              f"{1e3 * np.nanmean(meas[m]):5.2f} um ({np.nanmean(meas[m]) / std[m, 2].mean():.2f})  "
              f"q95 |actual - d| {1e3 * np.quantile(res, 0.95):4.1f} um  mean U_z {1e3 * u_z:4.1f} um")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else None)
