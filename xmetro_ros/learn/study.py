"""The study's learning pipeline end to end: data → splits → models → metrics → tables, plots, SHAP, ONNX.

``run_study(table, manifest, profile, seed, out_dir)`` writes into ``out_dir``:
* ``metrics.json`` (schema in docs/learning.md), ``tables.md`` (the study's Tables 1-3 for both splits),
* ``deviation_<axis>.png`` (predicted vs actual, PointNet), ``shap_<family>_<axis>.png`` (beeswarm),
* ``models/<family>/`` — one model set per family (ONNX + card), checked against the framework (≤ 1e-5 mm).
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..judge.attribution import explain, global_ranking
from ..judge.inference import AXES, ModelSet
from . import report
from .families import FAMILIES, TARGET_SCALE, check_family, get_profile
from .protocol import Split, cloud_split, config_keys, mae, r2, study_split, summarize
from .train import FittedModel, _jsonable, export_model_set, fit_model

__all__ = ["METRICS_SCHEMA", "load_data", "run_study", "time_model_set"]

METRICS_SCHEMA = "xmetro-metrics/1"
SPLIT_DOC = {
    "point": "the study's: 100 random points per cloud for training, five draws of 50 other points per cloud",
    "cloud": "held-out configurations: train on 100 points of every cloud of the other configurations, test on "
             "five draws of 50 points of each held-out cloud",
}


def load_data(profile: str = "quick", seed: int = 0, scans: list[Any] | None = None,
              source_manifest: dict | None = None, effects: dict | None = None,
              log: Callable[[str], None] = print, client: Any = None,
              sources: Sequence[Callable[[], list[Any]]] | None = None) -> tuple[Any, dict]:
    """Build the point table: from given ``scans`` (e.g. read from bags by ``xmetro train --data``, with their
    ``source_manifest``), or by simulating the profile's campaign with ``seed``. Returns (table, manifest).

    With a Dask ``client`` the scans are simulated (or read: ``sources``, callables returning scans, e.g. one per
    bag) and prepared on its workers by :func:`xmetro_ros.calibrate.dataset_dask.build_table_dask`: the same table."""
    from ..calibrate.dataset import build_table
    from ..judge.features import STUDY_FEATURES
    from ..preprocess import PreprocessConfig

    prof = get_profile(profile)
    if sources is not None or scans is not None:
        manifest = dict(source_manifest or {"source": "scans"})
    else:
        from ..sim.campaign import campaign_manifest, study_campaign

        kw = dict(prof.campaign)
        items = study_campaign(seed=seed, effects=effects, **kw)[:: prof.campaign_stride]
        t0 = time.perf_counter()
        if client is None:
            scans = [it.simulate() for it in _progress(items, "simulate", "scan")]
            log(f"simulated {len(scans)} scans in {time.perf_counter() - t0:.1f} s")
        else:
            from ..calibrate.dataset_dask import SimulateItems

            sources = [SimulateItems([it]) for it in items]  # simulated on the workers
        manifest = {"source": "simulated", "campaign_stride": prof.campaign_stride, "n_scans": len(items),
                    "campaign_args": {k: list(v) if isinstance(v, tuple) else v for k, v in kw.items()},
                    "campaign": campaign_manifest(items, seed=seed, effects=effects)}
    t0 = time.perf_counter()
    if client is not None:
        from ..calibrate.dataset_dask import ScanList, build_table_dask

        if sources is None:
            sources = [ScanList([s]) for s in scans or []]
        if not sources:
            raise ValueError("the data set has no scans")
        table = build_table_dask(sources, list(STUDY_FEATURES), client, PreprocessConfig(), progress=log)
    else:
        if not scans:
            raise ValueError("the data set has no scans")
        table = build_table(scans, list(STUDY_FEATURES), PreprocessConfig())
    log(f"feature table: {len(table.X)} points x {len(table.feature_names)} features "
        f"({time.perf_counter() - t0:.1f} s)")
    return table, manifest


def _progress(items, desc: str, unit: str, total: int | None = None):
    """A tqdm progress bar on stderr (hidden when stderr is not a terminal, e.g. in tests and CI logs)."""
    import sys

    from tqdm import tqdm

    return tqdm(items, desc=desc, unit=unit, total=total, file=sys.stderr, disable=None)


def _draw_metrics(model: FittedModel, X, y, cid, split: Split) -> dict[int, dict]:
    res: dict[int, dict] = {a: {"mae": [], "r2": []} for a in model.axes}
    preds = []
    for d in split.test:
        p = model.predict(X[d], cid[d])
        preds.append(p)
        for j, a in enumerate(model.axes):
            res[a]["mae"].append(mae(y[d, a], p[:, j]))
            res[a]["r2"].append(r2(y[d, a], p[:, j]))
    return {a: {"mae": summarize(v["mae"]), "r2": summarize(v["r2"])} for a, v in res.items()}


def _oracle(y, oracle, split: Split) -> dict[str, dict]:
    out: dict[str, dict] = {}
    if oracle is None:
        return out
    for a, ax in enumerate(AXES):
        m, r = [], []
        for d in split.test:
            ok = np.isfinite(oracle[d, a])
            if ok.any():
                m.append(mae(y[d][ok, a], oracle[d][ok, a]))
                r.append(r2(y[d][ok, a], oracle[d][ok, a]))
        if m:
            out[ax] = {"mae": summarize(m), "r2": summarize(r)}
    return out


def time_model_set(model_dir: Path, X: np.ndarray, n_points: int = 180_000, threads: Sequence[int] = (1, 2)) -> dict:
    """ms to predict an ``n_points`` scan (rows of X tiled) with ONNX Runtime, best of 2, per thread count."""
    rows = np.resize(np.asarray(X, np.float32), (n_points, X.shape[1]))
    out = {}
    for t in threads:
        ms = ModelSet.load(model_dir, threads=t)
        ms.predict(rows[:1000])
        best = np.inf
        for _ in range(2):
            t0 = time.perf_counter()
            ms.predict(rows)
            best = min(best, time.perf_counter() - t0)
        out[f"threads_{t}"] = round(best * 1e3, 1)
    return out


def run_study(
    table: Any,
    manifest: dict,
    profile: str = "quick",
    seed: int = 0,
    out_dir: str | Path = "out/train",
    families: Sequence[str] = FAMILIES,
    threads: int = 1,
    log: Callable[[str], None] = print,
    timing: bool = True,
    card_extra: dict | None = None,
    warm_start: dict[str, Any] | None = None,
) -> dict:
    """Run the protocol for ``families`` on ``table`` (X, y mm, cloud_id, oracle, feature_names); write the
    artefacts listed in the module doc; return the metrics dict. ``card_extra``: more card entries (the scanner,
    a calibration campaign, ``trained_by``), over the defaults. ``warm_start``: per PointNet family a fitted
    network both splits fine-tune instead of starting from random weights (``xmetro calibrate --prior``).

    Model ids are ``<family>-<profile>-s<seed>-<data hash>``: the same data and seed give the same id, other data
    another one (ids no longer collide across runs)."""
    prof = get_profile(profile)
    for f in families:
        check_family(f)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    X = np.asarray(table.X, np.float32)
    y = np.asarray(table.y, np.float64)
    cid = np.asarray(table.cloud_id)
    oracle = None if getattr(table, "oracle", None) is None else np.asarray(table.oracle, np.float64)
    names = list(table.feature_names)
    if len(X) == 0:
        raise ValueError("the data set has no points")
    for a, ax in enumerate(AXES):
        if not np.isfinite(y[:, a]).any():
            raise ValueError(f"the data set has no points with a finite {ax} error")
    splits = {
        "point": study_split(cid, 100, 50, prof.n_test_draws, seed),
        "cloud": cloud_split(cid, config_keys(X, names), 0.2, 100, 50, prof.n_test_draws, seed),
    }
    metrics: dict[str, Any] = {
        "schema": METRICS_SCHEMA, "profile": prof.name, "seed": seed, "manifest": manifest,
        "n_points": len(X), "n_clouds": len(np.unique(cid)), "feature_names": names,
        "splits": {}, "timings_s": {}, "models": {}, "shap": {},
    }
    point_models: dict[str, list[FittedModel]] = {}
    cloud_models: dict[str, list[FittedModel]] = {}
    bar = _progress(None, "train", "family", total=len(splits) * len(families))
    for split_name, split in splits.items():
        tr = split.train
        sm: dict[str, Any] = {"description": SPLIT_DOC[split_name], "n_train": len(tr),
                              "n_test_per_draw": len(split.test[0]), "n_draws": len(split.test),
                              "held_out_configurations": split.held_out_groups,
                              "oracle": _oracle(y, oracle, split), "models": {}}
        for fam in families:
            t0 = time.perf_counter()
            fitted: list[FittedModel] = []
            if fam == "pointnet_multi":
                prev = point_models.get(fam)
                params = prev[0].params if (prev and split_name != "point") else None
                fitted.append(fit_model(fam, X[tr], y[tr], seed=seed, profile=prof, groups=cid[tr], params=params,
                                        threads=threads, warm_start=(warm_start or {}).get(fam)))
            else:
                for a in range(3):
                    prev = point_models.get(fam)
                    params = prev[a].params if (prev and split_name != "point") else None
                    fitted.append(fit_model(fam, X[tr], y[tr, a], seed=seed, profile=prof, axes=(a,),
                                            groups=cid[tr], params=params, threads=threads))
            per_axis: dict[str, Any] = {}
            for m in fitted:
                for a, v in _draw_metrics(m, X, y, cid, split).items():
                    o = sm["oracle"].get(AXES[a])
                    v["ratio_to_oracle"] = (v["mae"]["mean"] / o["mae"]["mean"]) if o else None
                    v["params"] = _jsonable(m.params)
                    v["cv_mae"] = m.cv_mae
                    per_axis[AXES[a]] = v
            sm["models"][fam] = per_axis
            dt = time.perf_counter() - t0
            metrics["timings_s"][f"{split_name}/{fam}"] = round(dt, 1)
            def _ratio(r: float | None) -> str:  # real recordings have no oracle: say nothing rather than "xnan"
                return f" (x{r:.2f} oracle)" if r is not None and np.isfinite(r) else ""

            log(f"[{split_name}] {fam}: " + ", ".join(
                f"{ax} MAE {1000 * v['mae']['mean']:.1f} µm{_ratio(v['ratio_to_oracle'])}"
                for ax, v in per_axis.items()) + f"  ({dt:.0f} s)")
            if split_name == "point":
                point_models[fam] = fitted
            else:
                cloud_models[fam] = fitted
            bar.update(1)
        metrics["splits"][split_name] = sm
    bar.close()

    t0 = time.perf_counter()
    metrics["intervals"] = _intervals(cloud_models, X, y, cid, splits["cloud"], seed, threads)
    metrics["timings_s"]["intervals"] = round(time.perf_counter() - t0, 1)

    # ONNX model sets of the point-split models, checked against the framework.
    tr = splits["point"].train
    data_hash = hashlib.sha256(np.ascontiguousarray(X).tobytes() + np.ascontiguousarray(y).tobytes()).hexdigest()[:8]
    check_rows = splits["point"].test[0][: 2000]
    check_cloud = cid[check_rows] == cid[check_rows][0]
    for fam, fitted in point_models.items():
        t0 = time.perf_counter()
        extra = {
            "seed": seed, "profile": prof.name, "data_manifest": manifest,
            "metrics": {s: {ax: {k: metrics["splits"][s]["models"][fam][ax][k]["mean"] for k in ("mae", "r2")}
                            for ax in AXES} for s in metrics["splits"]},
            "trained_by": f"xmetro train --profile {prof.name} --seed {seed}",
            **(card_extra or {}),
        }
        d = export_model_set(fitted, out / "models" / fam, feature_names=names, X_train=X[tr],
                             card_extra=extra, model_id=f"{fam}-{prof.name}-s{seed}-{data_hash}",
                             check_X=X[check_rows][check_cloud])
        card = json.loads((d / "card.json").read_text())
        info = {"dir": str(Path("models") / fam), "onnx_max_abs_diff_mm": card["onnx_check"]["max_abs_diff_mm"],
                "bytes": int(sum(p.stat().st_size for p in d.glob("*.onnx")))}
        if timing and fam.startswith("pointnet"):
            info["ms_per_180k"] = time_model_set(d, X[splits["point"].test[0]])
        metrics["models"][fam] = info
        metrics["timings_s"][f"export/{fam}"] = round(time.perf_counter() - t0, 1)
        log(f"exported {fam}: {info}")

    _shap_and_plots(metrics, point_models, out, X, y, cid, splits["point"], names, prof, log,
                    clouds=getattr(table, "clouds", None))
    metrics["timings_s"]["total"] = round(time.perf_counter() - t_start, 1)
    (out / "metrics.json").write_text(json.dumps(_jsonable(metrics), indent=1))
    (out / "tables.md").write_text(report.tables_markdown(metrics))
    return metrics


INTERVALS_DOC = (
    "95 % intervals on the held-out configurations of the cloud split: every point of those clouds; the clouds "
    "are halved by cloud, each half calibrated on the other (split-conformal, crepes, scores |y - yhat| / "
    "(sigma_hat + 1 um)), hits and widths pooled. sigma_hat: PointNet 3-axis spread head; CatBoost: a "
    "RMSEWithUncertainty model with the family's parameters; other families: constant (absolute residuals)."
)


def _intervals(models: dict[str, list[FittedModel]], X, y, cid, split: Split, seed: int, threads: int) -> dict:
    """Coverage and mean width of calibrated 95 % intervals per family and axis (see INTERVALS_DOC)."""
    from .uncertainty import cross_conformal_by_cloud

    held = np.unique(cid[np.concatenate(split.test)])
    rows = np.flatnonzero(np.isin(cid, held))
    out: dict[str, Any] = {"description": INTERVALS_DOC, "n_clouds": len(held), "n_points": len(rows),
                           "families": {}}
    if len(held) < 2:
        return out
    for fam, fitted in models.items():
        pred = np.full((len(rows), 3), np.nan)
        sig = np.full((len(rows), 3), np.nan)
        for m in fitted:
            if fam == "catboost" and m.spread is None:
                m.spread = _catboost_spread(m, X[split.train], y[split.train, m.axes[0]], seed, threads)
            pred[:, list(m.axes)] = m.predict(X[rows], cid[rows])
            sig[:, list(m.axes)] = m.predict_sigma(X[rows], cid[rows])
        out["families"][fam] = cross_conformal_by_cloud(y[rows], pred, sig, cid[rows], seed=seed)
    return out


def _catboost_spread(m: FittedModel, X, y_mm, seed: int, threads: int):
    """CatBoost with the RMSEWithUncertainty loss (mean and variance per point), the family's parameters."""
    from catboost import CatBoostRegressor

    from .families import TARGET_SCALE as scale

    est = CatBoostRegressor(random_seed=seed, verbose=0, thread_count=threads, allow_writing_files=False,
                            loss_function="RMSEWithUncertainty", **{k: v for k, v in m.params.items()
                                                                    if k != "loss_function"})
    return est.fit(np.asarray(X, np.float32), np.asarray(y_mm, np.float64) * scale)


def _shap_and_plots(metrics, point_models, out: Path, X, y, cid, split: Split, names, prof, log,
                    clouds: list | None = None) -> None:
    t0 = time.perf_counter()
    test = split.test[0]
    test_clouds = np.unique(cid[test])
    n_clouds = max(1, prof.shap_points // max(1, int(np.sum(cid[test] == test_clouds[0]))))
    pick = np.random.default_rng(0).choice(test_clouds, min(n_clouds, len(test_clouds)), replace=False)
    # PointNet (study layout, else the compact one): our exact-additive explainer on the ONNX model set,
    # one cloud at a time (its points form the sets, as at inference).
    net = "pointnet" if "pointnet" in point_models else ("pointnet_multi" if "pointnet_multi" in point_models else None)
    if net:
        ms = ModelSet.load(out / "models" / net)
        Xl: list[np.ndarray] = []
        Sl: list[np.ndarray] = []
        for c in pick:
            rows = test[cid[test] == c]
            r = explain(ms, X[rows], np.asarray(ms.card["background"], np.float32), n_permutations=2,
                        max_background=prof.shap_background)
            Xl.append(X[rows])
            Sl.append(r.shap)
        Xs, S = np.concatenate(Xl), np.concatenate(Sl)
        metrics["shap"][net] = _rank_and_plot(S, Xs, names, net, out)
    if "catboost" in point_models:
        import shap

        rows = test[np.isin(cid[test], pick)]
        S = np.stack([shap.TreeExplainer(m.estimator).shap_values(X[rows]) / TARGET_SCALE
                      for m in point_models["catboost"]], axis=-1)
        metrics["shap"]["catboost"] = _rank_and_plot(S, X[rows], names, "catboost", out)
    # Deviation maps: one held-in sphere cloud, its non-training points, best PointNet vs actual.
    model = (point_models.get("pointnet") or point_models.get("pointnet_multi") or [None])
    if model[0] is not None:
        c = _map_cloud(pick, clouds)
        rows = np.setdiff1d(np.flatnonzero(cid == c), split.train)
        coords = X[rows][:, [names.index(n) for n in ("N_x", "N_y", "N_z")]] if "N_x" in names else X[rows][:, :3]
        pred = np.zeros((len(rows), 3))
        for m in model:
            pred[:, list(m.axes)] = m.predict(X[rows], cid[rows])
        for a, ax in enumerate(AXES):
            report.deviation_map(coords, y[rows, a], pred[:, a], a, out / f"deviation_{ax}.png",
                                 title=f"cloud {c}: {model[0].family}, on the unit normal sphere (N_x, N_y, N_z)")
    metrics["timings_s"]["shap_and_plots"] = round(time.perf_counter() - t0, 1)
    log(f"SHAP and plots: {time.perf_counter() - t0:.1f} s")


def _map_cloud(pick: np.ndarray, clouds: list | None):
    """The cloud for the deviation maps: the first picked sphere (where the table says), else the first pick."""
    for c in pick:
        try:
            if clouds is not None and "sphere" in json.dumps(clouds[int(c)].get("artifact", "")).lower():
                return c
        except (TypeError, IndexError, AttributeError):
            break
    return pick[0]


def _rank_and_plot(S: np.ndarray, Xs: np.ndarray, names: list[str], fam: str, out: Path) -> dict:
    res = {}
    for a, ax in enumerate(AXES):
        res[ax] = [[n, v] for n, v in global_ranking(S[:, :, a], names)]
        report.shap_beeswarm(S[:, :, a], Xs, names, out / f"shap_{fam}_{ax}.png",
                             title=f"SHAP summary, {fam}, {ax.upper()}-axis errors (mm)")
    return res

