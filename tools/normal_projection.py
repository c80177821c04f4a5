"""Per-axis intervals when d and U are carried onto the point's normal: ``python tools/normal_projection.py [OUT]``.

Issue 28 asks each axis' in-domain coverage of |actual − d| ≤ U to lie in [93, 97] %. The judge publishes the
model's own per-axis d and U. The target is a deviation from the nominal surface, so the true error lies along the
surface normal: on the parts study's level faces (median |N_x|, |N_y| ≤ 0.0033) X and Y carry 0.1-0.3 % of it, while
the model predicts X and Y errors of 0.5-1.2 µm there and U covers them widely (99-100 %).

This tool judges each scan once (``ScanHandler.process``, the shipped model) and scores five readings of the same
outputs against the simulator's truth (n: the judge's own unit normal of the point, ``Prepared.normals``, measured
on the scan, no CAD; U_n: U along the normal):

- ``published``: the per-axis d and U as the node publishes them;
- ``projected``: d' = (d·n)·n, U_n = Σ_k |n_k|·U_k (the published U along n, as ``parts.cad_judge`` carries it),
  U'_a = U_n·|n_a|;
- ``allowance``: ``projected`` with an allowance for the error of n's direction, U'_a = U_n·√(n_a² + θ²·(1 − n_a²)),
  θ = c·σ/h per point (σ the judge's measured noise along the normal, ``preprocess/noise.py``; h the scan's coarser
  grid spacing in mm: the scale of a plane fit's slope error), c per surface class (``judge/surface_class.py``);
- ``allowance_smoothed``: the same with n averaged over the grid cells within ±0.5 mm of the point (c refitted);
- ``noise_first``: U_n = m·σ, m per exposure level × surface class, then U'_a with the allowance (c refitted).

m and c are split-conformal (95 %, finite-sample rank): m on |(actual − d)·n| / σ, c on the θ each row and axis needs,
pooled over the axes, both on in-domain rows of calibration scans that are never scored: the calibration surfaces
(``scan/calibration_surfaces.py``: plate, groove and dimple, saddle, filleted ridge at many tilts) under every second
study setting and spheres of the training campaign's sizes under every third, on other seeds, 20,000 rows a scan.
They stand in for the product's calibration campaign; the card is not touched.

Scored scans: the parts study's seven parts as it presents them (seed 0, form error ±40 µm) and two spheres of the
training campaign's sizes (Ø 55 and 35 mm), each at the study's three settings. Per scan and reading: the in-domain
coverage per axis (also only on the points where |N_a| ≥ 0.05, i.e. where the axis carries the deviation) and along
the true normal N (|(actual − d)·N| ≤ Σ|N_k|·U_k), the MAE of actual − d per axis (µm) and the oracle's (expected −
actual: the simulator's noise-free error). Per scan: the true normal's median |N_a|; the median angle of the judge's
(and the smoothed) normal from N; along N, the simulator's noise s.d. against the judge's median σ, and the
published U_n against the 95 % quantile of the residual. Points: the judge's rows with a finite d and U, less the
injected outliers (the study counts every point with a finite d: its figures differ by up to 0.6 points). Writes
``OUT`` (default docs/results/parts/normal_projection.json), rendered in docs/parts-normal.md by
``tools/gen_reference.py``. About 3 minutes here.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
from scipy.ndimage import uniform_filter

from xmetro_ros.judge import flags as fl
from xmetro_ros.judge.conditions import exposure_edges
from xmetro_ros.judge.inference import ModelSet
from xmetro_ros.judge.scan_handler import ScanHandler
from xmetro_ros.judge.surface_class import SURFACE_CLASSES
from xmetro_ros.learn.conformal import conformal_multiplier
from xmetro_ros.parts.study import DEFAULT_PARTS, DEFAULT_SETTINGS, FORM_UM, PRESENTATION
from xmetro_ros.scan.artifacts import Sphere
from xmetro_ros.scan.calibration_surfaces import surface_campaign
from xmetro_ros.scan.generated_parts import make_part
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim import simulate_scan

ROOT = Path(__file__).resolve().parents[1]
SMOOTH_MM = 0.5  # half-width of the normal's smoothing window
LEVEL = 0.95
CAL_SEED = 424242  # the calibration scans' seeds (the scored scans use 0)
CAL_ROWS = 20_000  # rows a calibration scan
CARRY = 0.05  # |N_a| from which axis a counts as carrying the deviation (~3° from the perpendicular plane)


def u_along(u: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(M,) U along the unit normals n (M, 3) from the per-axis U (M, 3): Σ_k |n_k|·U_k (``parts.cad_judge``'s)."""
    return np.einsum("ij,ij->i", np.abs(n), u)


def project(d: np.ndarray, n: np.ndarray, un: np.ndarray, theta: np.ndarray | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
    """(d', U') (M, 3) mm: d (M, 3) carried onto the unit normals n (M, 3), d' = (d·n)·n, and U along the normal
    ``un`` (M,) mm spread over the axes, U'_a = U_n·|n_a|; with ``theta`` (M,) rad, the allowance for n's direction
    error, U'_a = U_n·√(n_a² + θ²·(1 − n_a²))."""
    dn = np.einsum("ij,ij->i", d, n)
    w = np.abs(n) if theta is None else np.sqrt(n**2 + theta[:, None] ** 2 * (1.0 - n**2))
    return dn[:, None] * n, un[:, None] * w


def smooth_normals(prepared: Any, settings: ScanSettings, radius_mm: float = SMOOTH_MM) -> np.ndarray:
    """(M, 3) unit normals of the kept points averaged over the grid cells within ±``radius_mm`` (rows: profiles
    along the scan, columns: points along the laser line), then normalised."""
    h, w = prepared.shape
    idx = np.asarray(prepared.index)
    ky = max(1, round(radius_mm * settings.direction_density))
    kx = max(1, round(radius_mm * settings.lateral_density))
    acc = np.zeros((3, h * w))
    acc[:, idx] = np.asarray(prepared.normals, np.float64).T
    box = np.stack([uniform_filter(a.reshape(h, w), size=(2 * ky + 1, 2 * kx + 1), mode="constant") for a in acc])
    out = box.reshape(3, -1)[:, idx].T
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def judge(h: ScanHandler, man: Any, settings: ScanSettings, seed: int = 0, rows: int | None = None
          ) -> dict[str, np.ndarray]:
    """One scan of ``man`` judged once: per row d, U, the judge's normal n and the smoothed one, the truth (actual
    error, true normal N, expected error), in-domain mask, surface class and θ's scale σ/h; ``rows``: at most that
    many rows, drawn at random (seeded)."""
    scan = simulate_scan(man, settings, scanner=h.scanner, seed=seed)
    res = h.process(scan)
    idx = np.asarray(res.prepared.index)
    inj = (np.zeros(len(idx), bool) if scan.injected_outlier is None
           else np.asarray(scan.injected_outlier).reshape(-1)[idx])
    d, u = res.predictions, res.row_uncertainty
    assert u is not None and res.noise is not None and res.surface_class is not None
    use = np.flatnonzero(np.isfinite(d).all(axis=1) & np.isfinite(u).all(axis=1) & ~inj)
    if rows is not None and len(use) > rows:
        use = np.sort(np.random.default_rng(seed).choice(use, rows, replace=False))
    p = np.asarray(res.scan.points, np.float64).reshape(-1, 3)[idx][use]
    spacing = 1.0 / min(settings.lateral_density, settings.direction_density)
    return {"d": d[use], "u": u[use], "n": np.asarray(res.prepared.normals, np.float64)[use],
            "ns": smooth_normals(res.prepared, settings)[use], "actual": man.errors(p), "N": man.normals(p),
            "expected": np.asarray(scan.expected_error).reshape(-1, 3)[idx][use],
            "ind": (res.flags[idx][use] & fl.FLAG_OUT_OF_DOMAIN) == 0, "cls": np.asarray(res.surface_class)[use],
            "sigma": np.asarray(res.noise, np.float64)[use], "exposure_ms": np.full(len(use), settings.exposure_ms),
            "scale": np.nan_to_num(np.asarray(res.noise)[use], nan=0.0) / spacing}


def _conformal(v: np.ndarray) -> float:
    """The LEVEL split-conformal quantile of the scores ``v`` (rank ⌈(n + 1)·LEVEL⌉), through the product's own
    crepes wrapper so the tool and the card agree on the rank."""
    return conformal_multiplier(np.asarray(v, np.float64).ravel(), np.ones(np.size(v)), LEVEL)


def needed_theta(r: dict[str, np.ndarray], n: np.ndarray, un: np.ndarray) -> np.ndarray:
    """(M, 3) the θ each row and axis needs for |actual − d'| ≤ U' (0 where the projection alone covers it), for
    the normals n and U along them ``un``."""
    dp, _ = project(r["d"], n, un)
    s2 = (((r["actual"] - dp) / un[:, None]) ** 2 - n**2) / np.maximum(1.0 - n**2, 1e-12)
    return np.sqrt(np.maximum(s2, 0.0))


def fit_allowance(cal: list[dict[str, np.ndarray]], nkey: str, u_n: Any) -> dict[int, float]:
    """Conformal c per surface class: the LEVEL quantile of needed θ / (σ/h) over the in-domain rows, axes pooled;
    ``u_n(r, n)``: U along the normals n of the rows r."""
    ratio = np.concatenate([(needed_theta(r, r[nkey], u_n(r, r[nkey])) / np.maximum(r["scale"], 1e-9)[:, None])[
        r["ind"]] for r in cal])
    cls = np.concatenate([r["cls"][r["ind"]] for r in cal])
    return {int(k): _conformal(ratio[cls == k].ravel()) for k in np.unique(cls)}


def _theta(r: dict[str, np.ndarray], c: dict[int, float]) -> np.ndarray:
    fallback = max(c.values())  # a class the calibration never saw: the widest
    return np.array([c.get(int(k), fallback) for k in r["cls"]]) * r["scale"]


def _group(r: dict[str, np.ndarray], edges: list[float]) -> np.ndarray:
    """(M,) noise-multiplier group of each row: exposure level × surface class."""
    return np.searchsorted(edges, r["exposure_ms"]) * 100 + r["cls"].astype(np.int64) + 1


def fit_noise_multipliers(cal: list[dict[str, np.ndarray]], edges: list[float]) -> dict[int, float]:
    """U along the normal from the measured noise: per exposure level × surface class, the LEVEL quantile of
    |(actual − d)·n| / σ over the in-domain rows with a measured σ (n the judge's normal)."""
    score, grp = [], []
    for r in cal:
        ok = r["ind"] & (r["sigma"] > 0)
        rn = np.einsum("ij,ij->i", r["actual"] - r["d"], r["n"])
        score.append(np.abs(rn[ok]) / r["sigma"][ok])
        grp.append(_group(r, edges)[ok])
    v, g = np.concatenate(score), np.concatenate(grp)
    return {int(k): _conformal(v[g == k]) for k in np.unique(g)}


def noise_u_n(mult: dict[int, float], edges: list[float]) -> Any:
    """``u_n(r, n)`` for the noise-first reading: multiplier × σ; the published U along n where no σ was measured
    or the group was never calibrated."""
    def u_n(r: dict[str, np.ndarray], n: np.ndarray) -> np.ndarray:
        m = np.array([mult.get(int(k), np.nan) for k in _group(r, edges)])
        out = m * r["sigma"]
        return np.where(np.isfinite(out) & (out > 0), out, u_along(r["u"], n))
    return u_n


def _scores(r: dict[str, np.ndarray], d: np.ndarray, u: np.ndarray) -> dict[str, Any]:
    ind, N = r["ind"], r["N"]
    res = r["actual"] - d
    cov = (np.abs(res) <= u)[ind].mean(axis=0)
    cov_n = (np.abs(np.einsum("ij,ij->i", res, N)) <= np.einsum("ij,ij->i", np.abs(N), u))[ind].mean()
    # per axis on the points whose true normal has a component of at least CARRY on it (the axis carries ≥ 5 % of
    # the deviation; below, its true error is a few hundredths of a µm): None where fewer than 1,000 such points
    carry = (np.abs(N) >= CARRY) & ind[:, None]
    cov_c = [float((np.abs(res[:, a]) <= u[:, a])[carry[:, a]].mean()) if carry[:, a].sum() >= 1000 else None
             for a in range(3)]
    return {"coverage_xyz": [float(c) for c in cov], "coverage_normal": float(cov_n), "coverage_xyz_carrying": cov_c,
            "mae_um": [float(x) for x in 1e3 * np.abs(res).mean(axis=0)],
            "oracle_mae_um": [float(x) for x in 1e3 * np.abs(r["expected"] - r["actual"]).mean(axis=0)]}


def _angle_deg(n: np.ndarray, N: np.ndarray) -> float:
    c = np.abs(np.einsum("ij,ij->i", n / np.linalg.norm(n, axis=1, keepdims=True), N))
    return float(np.degrees(np.median(np.arccos(np.clip(c, 0.0, 1.0)))))


def readings(r: dict[str, np.ndarray], c: dict[str, dict[int, float]], u_noise: Any) -> dict[str, Any]:
    """The five readings' scores of one judged scan (``c``: the allowance's c per reading, ``u_noise``: the
    noise-first U along the normal)."""
    n, ns = r["n"], r["ns"]
    out: dict[str, Any] = {
        "published": _scores(r, r["d"], r["u"]),
        "projected": _scores(r, *project(r["d"], n, u_along(r["u"], n))),
        "allowance": _scores(r, *project(r["d"], n, u_along(r["u"], n), _theta(r, c["allowance"]))),
        "allowance_smoothed": _scores(r, *project(r["d"], ns, u_along(r["u"], ns), _theta(r, c["allowance_smoothed"]))),
        "noise_first": _scores(r, *project(r["d"], n, u_noise(r, n), _theta(r, c["noise_first"])))}
    out["true_normal_median_abs"] = [float(x) for x in np.median(np.abs(r["N"]), axis=0)]
    # along the true normal, in domain (µm): the simulator's noise against the judge's measured σ, and the published
    # U along the normal against the 95 % quantile of the residual it should cover
    ind, N = r["ind"], r["N"]
    out["along_normal_um"] = {
        "true_noise_sd": float(1e3 * np.einsum("ij,ij->i", r["actual"] - r["expected"], N)[ind].std()),
        "measured_noise_median": float(1e3 * np.nanmedian(r["sigma"][ind])),
        "published_u_median": float(1e3 * np.median(u_along(r["u"], N)[ind])),
        "residual_p95": float(1e3 * np.percentile(np.abs(np.einsum("ij,ij->i", r["actual"] - r["d"], N))[ind], 95))}
    out["normal_error_median_deg"] = {"judge": _angle_deg(n, r["N"]), "smoothed": _angle_deg(ns, r["N"])}
    return out


def _in(c: list[float], lo: float = 0.93, hi: float = 0.97) -> bool:
    return all(lo <= x <= hi for x in c)


READINGS = ("published", "projected", "allowance", "allowance_smoothed", "noise_first")


def main(out: str | None = None) -> None:
    sc = ScannerModel.load()
    ms = ModelSet.load()
    h = ScanHandler(ms, sc)
    cal = [judge(h, a, st, sd, rows=CAL_ROWS) for a, st, sd, _ in surface_campaign(sc, CAL_SEED, stride=2)]
    for k, setting in enumerate(sc.study_configurations()[::3]):
        for j, radius in enumerate((27.5, 17.5)):
            cal.append(judge(h, Sphere(radius, (0.0, 0.0, 0.0)), setting, CAL_SEED + 100 * j + k, rows=CAL_ROWS))
    exposures = sorted({st.exposure_ms for st in sc.study_configurations()})
    edges = exposure_edges(exposures)[1:-1]  # the interior edges: level i below edges[i]
    mult = fit_noise_multipliers(cal, edges)
    u_noise = noise_u_n(mult, edges)
    published = lambda r, n: u_along(r["u"], n)  # noqa: E731
    c = {"allowance": fit_allowance(cal, "n", published), "allowance_smoothed": fit_allowance(cal, "ns", published),
         "noise_first": fit_allowance(cal, "n", u_noise)}
    named = {key: {SURFACE_CLASSES[k] if k >= 0 else "none": round(v, 4) for k, v in ck.items()}
             for key, ck in c.items()}
    named_mult = {f"{exposures[k // 100]:g} ms, {SURFACE_CLASSES[k % 100 - 1] if k % 100 else 'none'}": round(v, 3)
                  for k, v in mult.items()}
    print(f"{len(cal)} calibration scans; allowance c per surface class: {named}; noise multipliers: {named_mult}")
    arts: dict[str, Any] = {p: make_part(p, form_um=FORM_UM).transformed(PRESENTATION) for p in DEFAULT_PARTS}
    arts.update({"sphere R27.5": Sphere(27.5, (0.0, 0.0, 0.0)), "sphere R17.5": Sphere(17.5, (0.0, 0.0, 0.0))})
    rows = []
    print("| scan | setting | " + " | ".join(f"{k} x / y / z / normal (%)" for k in READINGS)
          + " | median |N_x|, |N_y| | normal error judge / smoothed (°) |")
    print("|---|---|" + "---|" * (len(READINGS) + 2))
    for name, man in arts.items():
        for st in DEFAULT_SETTINGS:
            r = judge(h, man, ScanSettings(*st))
            row = {"scan": name, "settings": list(st), "points": len(r["d"]), "in_domain": float(r["ind"].mean()),
                   **readings(r, c, u_noise)}
            rows.append(row)
            cells = [" / ".join(f"{100 * x:.1f}" for x in [*row[k]["coverage_xyz"], row[k]["coverage_normal"]])
                     for k in READINGS]
            tn, ne = row["true_normal_median_abs"], row["normal_error_median_deg"]
            print(f"| {name} | {'/'.join(f'{v:g}' for v in st)} | " + " | ".join(cells)
                  + f" | {tn[0]:.4f}, {tn[1]:.4f} | {ne['judge']:.2f} / {ne['smoothed']:.2f} |", flush=True)
    def n_met(k: str, spheres: bool, carrying: bool = False) -> int:
        return sum(_in([*(c for c in r[k]["coverage_xyz_carrying" if carrying else "coverage_xyz"] if c is not None),
                        r[k]["coverage_normal"]]) for r in rows if r["scan"].startswith("sphere") == spheres)

    met = {k: {"parts": n_met(k, False), "spheres": n_met(k, True), "parts_carrying_axes": n_met(k, False, True),
               "spheres_carrying_axes": n_met(k, True, True)} for k in READINGS}
    print("\nrows with x, y, z and the normal in [93, 97] % (of 21 part rows + 6 sphere rows; then counting an axis "
          f"only on points with |N_a| >= {CARRY}): " + ", ".join(
              f"{k} {v['parts']} + {v['spheres']} ({v['parts_carrying_axes']} + {v['spheres_carrying_axes']})"
              for k, v in met.items()))
    path = Path(out) if out else ROOT / "docs" / "results" / "parts" / "normal_projection.json"
    path.write_text(json.dumps({"model": ms.id, "seed": 0, "form_um": FORM_UM, "smooth_mm": SMOOTH_MM,
                                "calibration": {"scans": len(cal), "seed": CAL_SEED, "rows_per_scan": CAL_ROWS,
                                                "c_per_class": named, "noise_multipliers": named_mult},
                                "rows_met": met, "rows": rows}, indent=1) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else None)
