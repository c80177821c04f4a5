"""`xmetro fleet predict` and the learning table on Dask: a local cluster of 2 worker processes (loopback only), or
an existing cluster given by address (``--scheduler``), gives the single-process results — the same output bags byte
for byte, the same tables array for array; a corrupt bag is reported and the others complete; a second run resumes
(done bags skipped); the summary holds the per-axis uncertainty U of every judged scan."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from xmetro_ros.apps import fleet
from xmetro_ros.apps.predict import predict_bag
from xmetro_ros.ros.node_outputs import read_outputs

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "bags" / "demo.mcap"
REGRESSION = ROOT / "bags" / "regression.mcap"

pytestmark = pytest.mark.timeout(300)


@pytest.fixture(scope="module")
def client():
    with fleet.dask_client(workers=2) as c:
        assert len(c.scheduler_info()["workers"]) == 2
        assert all(a.startswith("tcp://127.0.0.1:") for a in c.scheduler_info()["workers"])
        yield c


@pytest.fixture(scope="module")
def single(tmp_path_factory):
    """The single-process path (``xmetro predict --deterministic``) into the fleet's output file names (a bag
    records its own file name): name → output bag."""
    d = tmp_path_factory.mktemp("single")
    out = {}
    for name, src in [("cellA/day1", DEMO), ("cellB/day1", REGRESSION), ("cellB/day2", DEMO)]:
        ref = (d / name).with_suffix(".mcap")
        ref.parent.mkdir(parents=True, exist_ok=True)
        predict_bag(src, ref, deterministic=True)
        out[name] = ref
    return out


@pytest.fixture(scope="module")
def fleet_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("fleet")
    inp = d / "in"
    (inp / "cellA").mkdir(parents=True)
    (inp / "cellB").mkdir()
    shutil.copy(DEMO, inp / "cellA" / "day1.mcap")
    shutil.copy(REGRESSION, inp / "cellB" / "day1.mcap")  # same name, other cell: no collision
    shutil.copy(DEMO, inp / "cellB" / "day2.mcap")
    rng = np.random.default_rng(0)
    (inp / "cellA" / "garbage.mcap").write_bytes(rng.integers(0, 256, 50_000, dtype=np.uint8).tobytes())
    data = DEMO.read_bytes()
    (inp / "cellA" / "truncated.mcap").write_bytes(data[: len(data) // 2])  # a recording cut off mid-write
    return d


def test_find_and_plan(fleet_dir):
    inp = fleet_dir / "in"
    bags = fleet.find_bags([str(inp / "cellA"), str(inp / "cellB" / "*.mcap")])
    assert [b.name for b in bags] == ["day1.mcap", "garbage.mcap", "truncated.mcap", "day1.mcap", "day2.mcap"]
    jobs = fleet.plan_jobs(bags, fleet_dir / "out", [("*cellB/day2*", "line7")])
    assert [j.name for j in jobs] == ["cellA/day1", "cellA/garbage", "cellA/truncated", "cellB/day1", "cellB/day2"]
    assert [j.cell for j in jobs] == ["cellA", "cellA", "cellA", "cellB", "line7"]
    with pytest.raises(FileNotFoundError):
        fleet.find_bags([str(inp / "nope*.mcap")])


def test_fleet_predict_identical_to_single_process_and_resumes(client, fleet_dir, single):
    out = fleet_dir / "out"
    jobs = fleet.plan_jobs(fleet.find_bags([str(fleet_dir / "in")]), out)
    lines: list[str] = []
    res = fleet.run_fleet(jobs, client, out, deterministic=True, log=lines.append)
    status = {b["name"]: b for b in res.bags}
    assert {k: v["status"] for k, v in status.items()} == {
        "cellA/day1": "done", "cellA/garbage": "failed", "cellA/truncated": "damaged", "cellB/day1": "done",
        "cellB/day2": "done"}
    assert "not an MCAP file" in status["cellA/garbage"]["error"]
    assert status["cellA/truncated"]["losses"]  # what was lost is reported, what was readable is judged
    assert res.workers == 2 and len({b["worker_pid"] for b in res.bags}) == 2  # both workers took bags
    assert len(lines) == 5 and all(f"/{len(jobs)}]" in s for s in lines)  # one progress line per bag
    assert not (out / "cellA" / "garbage.mcap").exists()
    assert not (out / "cellA" / ".partial").exists()  # no empty side directory left by the failed bag

    # The single-process path (xmetro predict), into the same file names: the same bytes.
    for name, ref in single.items():
        assert (out / f"{name}.mcap").read_bytes() == ref.read_bytes(), name
        assert status[name]["scans"] == len(read_outputs(ref))

    # The summary: one row per judged scan, the ScanQuality values of the output bags.
    df = pd.read_parquet(res.summary)
    import dask.dataframe as dd

    pd.testing.assert_frame_equal(dd.read_parquet(res.summary).compute().reset_index(drop=True), df,
                                  check_dtype=False)  # dask reads strings with pd.NA as missing value
    assert len(df) == sum(b["scans"] for b in res.bags) and set(df["bag"]) == set(status) - {"cellA/garbage"}
    for name in ("cellB/day1", "cellA/truncated"):
        qs = [o.quality for o in read_outputs(out / f"{name}.mcap")]
        d = df[df["bag"] == name].sort_values("scan")
        assert len(d) == len(qs) > 0
        for a, axis in enumerate(fleet.AXES):
            assert np.array_equal(d[f"p95_abs_error_{axis}"].to_numpy(), [q.p95_abs_error[a] for q in qs])
            assert np.array_equal(d[f"mean_abs_error_{axis}"].to_numpy(), [q.mean_abs_error[a] for q in qs])
        for a, axis in enumerate(fleet.AXES):  # U: expanded uncertainty per axis (the shipped model is calibrated)
            for stat in ("p95", "mean"):
                col = d[f"{stat}_uncertainty_{axis}"].to_numpy()
                assert np.array_equal(col, [getattr(q, f"{stat}_uncertainty")[a] for q in qs])
                judged = (d["verdict_name"] != "ERROR").to_numpy()
                assert judged.any() and np.isfinite(col[judged]).all() and (col[judged] > 0).all()
        assert d["verdict"].tolist() == [int(q.verdict) for q in qs]
        assert d["points_received"].tolist() == [int(q.points_received) for q in qs]
        assert d["settings_exposure_time"].tolist() == [q.settings.exposure_time for q in qs]
        assert (d["cell"] == name.split("/")[0]).all() and (d["processing_latency"] == 0.0).all()
        assert d["time"].dt.tz is not None
    html = res.overview.read_text()
    assert "data:image/png;base64," in html and "cellA/garbage" in html and "failed" in html

    # Resume: the done bags are skipped (files untouched), the failed one is tried again.
    mtime = (out / "cellA" / "day1.mcap").stat().st_mtime_ns
    res2 = fleet.run_fleet(jobs, client, out, deterministic=True)
    assert {b["name"]: b["status"] for b in res2.bags} == {
        "cellA/day1": "skipped", "cellA/garbage": "failed", "cellA/truncated": "skipped", "cellB/day1": "skipped",
        "cellB/day2": "skipped"}
    assert (out / "cellA" / "day1.mcap").stat().st_mtime_ns == mtime
    assert len(pd.read_parquet(res2.summary)) == len(df)
    # The rerun keeps the damage record of the run that found it (issue 27): still lost data, still reported.
    trunc = next(b for b in res2.bags if b["name"] == "cellA/truncated")
    assert trunc["damaged"] and trunc["losses"] == status["cellA/truncated"]["losses"]
    assert res2.lost_data == 1 and not any(b.get("damaged") for b in res2.bags if b["name"] != "cellA/truncated")


def test_fleet_cli(fleet_dir, tmp_path, capsys):
    from xmetro_ros.apps.cli import main

    out = tmp_path / "out"
    rc = main(["fleet", "predict", str(fleet_dir / "in" / "cellB"), "--out-dir", str(out), "--workers", "1",
               "--param", "threads=1"])
    assert rc == 0
    assert "2 done" in capsys.readouterr().out
    assert len(pd.read_parquet(out / "summary.parquet")) == 8
    assert main(["fleet", "predict", str(fleet_dir / "in"), "--out-dir", str(out), "--param", "nope=1"]) == 2


def test_fleet_cli_existing_cluster_by_address(fleet_dir, single, tmp_path, capsys):
    """``--scheduler tcp://...``: an existing cluster (its own worker process, started here) gives the output bags
    of the single-process path byte for byte, and the summary with its uncertainty columns."""
    import logging

    from distributed import LocalCluster

    from xmetro_ros.apps.cli import main

    out = tmp_path / "out"
    with LocalCluster(processes=True, n_workers=1, threads_per_worker=1, host="127.0.0.1", dashboard_address=None,
                      silence_logs=logging.ERROR) as cluster:
        addr = cluster.scheduler_address
        assert addr.startswith("tcp://127.0.0.1:")
        rc = main(["fleet", "predict", str(fleet_dir / "in" / "cellB"), "--out-dir", str(out), "--scheduler", addr,
                   "--deterministic"])
    cap = capsys.readouterr()
    assert rc == 0, cap.out + cap.err
    assert addr in cap.err and "2 done" in cap.out and "on 1 worker(s)" in cap.out
    for name in ("day1", "day2"):
        assert (out / f"{name}.mcap").read_bytes() == single[f"cellB/{name}"].read_bytes(), name
    df = pd.read_parquet(out / "summary.parquet")
    assert len(df) == 8 and df["bag"].tolist() == ["day1"] * 4 + ["day2"] * 4
    ucols = [f"{s}_uncertainty_{a}" for s in ("p95", "mean") for a in fleet.AXES]
    assert set(ucols) <= set(df.columns)
    judged = df[df["verdict_name"] != "ERROR"]
    assert len(judged) and np.isfinite(judged[ucols].to_numpy()).all()


def test_build_table_dask_equals_build_table(client):
    from test_dataset import grid_scan

    from xmetro_ros.calibrate import dataset as D
    from xmetro_ros.calibrate.dataset_dask import ScanList, build_table_dask
    from xmetro_ros.judge.features import STUDY_FEATURES
    from xmetro_ros.scan.artifacts import Cylinder, Sphere
    from xmetro_ros.scan.scanner import ScanSettings

    scans = [grid_scan(Sphere(20.0), ScanSettings(6, 3, 0.1)),
             grid_scan(Sphere(20.0), ScanSettings(10, 4, 0.5), shift=0.05),
             grid_scan(Cylinder(15.0), ScanSettings(15, 5, 2.0)),
             grid_scan(Sphere(25.0), ScanSettings(8, 3, 1.0), h=30)]
    names = [*STUDY_FEATURES, "field_intensity"]
    ref = D.build_table(scans, names, max_points_per_cloud=700, seed=3)
    for sources in ([ScanList(scans[:1]), ScanList(scans[1:3]), ScanList(scans[3:])], [ScanList([s]) for s in scans]):
        tab = build_table_dask(sources, names, client, max_points_per_cloud=700, seed=3)
        for k in ("X", "y", "cloud_id", "oracle", "point_index"):
            assert np.array_equal(getattr(tab, k), getattr(ref, k), equal_nan=True), k
        assert tab.clouds == ref.clouds and tab.feature_names == ref.feature_names
    assert len(ref) < sum(s.points.reshape(-1, 3).shape[0] for s in scans)  # sampling took place


def test_load_data_on_dask_equals_single_process(client):
    from xmetro_ros.learn.study import load_data

    ref, m_ref = load_data("micro", 0, log=lambda s: None)
    tab, m = load_data("micro", 0, client=client, log=lambda s: None)
    for k in ("X", "y", "cloud_id", "oracle", "point_index"):
        assert np.array_equal(getattr(tab, k), getattr(ref, k), equal_nan=True), k
    assert tab.clouds == ref.clouds and m == m_ref


def test_train_data_from_bags_via_scheduler_address(client, tmp_path):
    """``xmetro train --data DIR --scheduler ADDR``: bags read on the workers of an existing cluster (the module's,
    by address) give the table of the single-process path."""
    import argparse

    from test_dataset import grid_scan

    from xmetro_ros.apps.train import _load_data_dask, _read_data
    from xmetro_ros.learn.study import load_data
    from xmetro_ros.ros.scan_io import write_scans
    from xmetro_ros.scan.artifacts import Cylinder, Sphere
    from xmetro_ros.scan.scanner import ScanSettings

    scans = [grid_scan(Sphere(20.0), ScanSettings(6, 3, 0.1)), grid_scan(Cylinder(15.0), ScanSettings(15, 5, 2.0)),
             grid_scan(Sphere(25.0), ScanSettings(10, 4, 0.5), shift=0.05)]
    write_scans(tmp_path / "a.mcap", scans[:2], {"part": "a"})
    write_scans(tmp_path / "b.mcap", scans[2:], {"part": "b"})
    ref, m_ref = load_data("micro", 0, *_read_data(tmp_path)[:1], source_manifest=_read_data(tmp_path)[1],
                           log=lambda s: None)
    args = argparse.Namespace(profile="micro", seed=0, data=str(tmp_path), scheduler=client.scheduler.address,
                              workers=None)
    tab, m = _load_data_dask(args)
    for k in ("X", "y", "cloud_id", "oracle", "point_index"):
        assert np.array_equal(getattr(tab, k), getattr(ref, k), equal_nan=True), k
    assert tab.clouds == ref.clouds and m == m_ref and len(tab.clouds) == 3


def test_overview_without_time_stamps_and_in_micrometres(tmp_path):
    """Issue 27: scans with header stamp 0 are no 1970 dates — off the time axis (counted in the tables), or, when
    no scan has a stamp, plotted in the fleet's order; errors in µm."""
    from xmetro_ros.apps.fleet_report import write_overview

    def summary(stamps: list[int]) -> Path:
        n = len(stamps)
        df = pd.DataFrame({"stamp_ns": stamps, "cell": ["c"] * n, "bag": ["b"] * n, "verdict_name": ["OK"] * n,
                           **{f"p95_abs_error_{a}": [2.5e-5] * n for a in fleet.AXES}})
        df["time"] = pd.to_datetime(df["stamp_ns"], unit="ns", utc=True)
        p = tmp_path / f"s{n}_{stamps[0]}.parquet"
        df.to_parquet(p, index=False)
        return p

    t0 = 1_735_689_600_000_000_000  # 2025-01-01
    html = write_overview(summary([0, 0, t0, t0 + 2_000_000_000]), tmp_path / "a.html").read_text()
    assert "1970" not in html and "2025-01-01" in html and "2 scans without a time stamp" in html
    assert "median p95 x (µm)" in html and "<td>25.0</td>" in html
    html = write_overview(summary([0, 0, 0]), tmp_path / "b.html").read_text()
    assert "1970" not in html and "no scan has a time stamp" in html
