"""`xmetro loop --workers / --scheduler`: the loop's inputs (bags read scan by scan → pre-process → features →
targets) prepared on Dask workers (a local cluster of 2 worker processes, loopback only) are the single-process
table array for array, and the loop's report is the same."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_loop import _cli, sim_scan

from xmetro_ros.apps import fleet
from xmetro_ros.loop.data import LoopData, LoopInputError
from xmetro_ros.loop.inputs import load_inputs
from xmetro_ros.loop.inputs_dask import load_inputs_dask
from xmetro_ros.ros.scan_io import iter_scans, read_scans, write_scans

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def client():
    with fleet.dask_client(workers=2) as c:
        assert all(a.startswith("tcp://127.0.0.1:") for a in c.scheduler_info()["workers"])
        yield c


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    d = tmp_path_factory.mktemp("loopbags")
    return [write_scans(d / "a.mcap", [sim_scan(500 + k, "pass", 0.03) for k in range(3)]),
            write_scans(d / "b.mcap", [sim_scan(503 + k, "pass", 0.03) for k in range(3)])]


def assert_same(a: LoopData, b: LoopData) -> None:
    for k in ("points", "normals", "errors", "X", "group", "order"):
        x, y = getattr(a, k), getattr(b, k)
        assert x.dtype == y.dtype and np.array_equal(x, y), k
    for k in ("fields", "geometry"):
        x, y = getattr(a, k), getattr(b, k)
        assert list(x) == list(y) and all(np.array_equal(x[f], y[f]) and x[f].dtype == y[f].dtype for f in x), k
    assert (a.feature_names, a.group_names, a.source, a.hold_by, a.artifact) == (
        b.feature_names, b.group_names, b.source, b.hold_by, b.artifact)


def test_loop_inputs_on_dask_equal_single_process(client, bags):
    ref = load_inputs(bags, None, read_bag=read_scans)  # the former single-process path: whole bags
    assert len(ref.groups) == 6 and ref.group_names[3] == "b#0"
    assert_same(load_inputs(bags, None, read_bag=iter_scans), ref)  # streamed scan by scan
    lines: list[str] = []
    data = load_inputs_dask(bags, None, None, client, read_bag=iter_scans, progress=lines.append)
    assert_same(data, ref)
    assert len(lines) == 2 and all("3 group(s)" in s for s in lines)

def test_loop_inputs_on_dask_artifact_and_features(client, tmp_path):
    """An overriding artifact (centre fitted per scan) and a given model's features: the same on both paths."""
    bag = write_scans(tmp_path / "r22.mcap", [sim_scan(s, "pass", 0.03) for s in (500, 506)])  # radius 22.5
    feats = ["N_x", "N_y", "N_z", "Inc", "field_intensity"]
    ref = load_inputs([bag], "sphere:radius=22.5,center=fit", feats, read_bag=read_scans)
    assert ref.feature_names == feats and ref.artifact["fit_center"] is True
    assert_same(load_inputs_dask([bag], "sphere:radius=22.5,center=fit", feats, client, read_bag=iter_scans), ref)


def test_loop_inputs_on_dask_errors(client, bags, tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not a bag at all")
    with pytest.raises(ValueError) as single:
        load_inputs([bags[0], bad], None, read_bag=iter_scans)
    with pytest.raises(ValueError) as dask:
        load_inputs_dask([bags[0], bad], None, None, client, read_bag=iter_scans)
    assert type(dask.value) is type(single.value)
    with pytest.raises(LoopInputError, match="does not exist"):
        load_inputs_dask([tmp_path / "missing.mcap"], None, None, client, read_bag=iter_scans)


def test_loop_cli_scheduler_same_report(client, bags, tmp_path, capsys):
    args = [*map(str, bags), "--n-perm", "29", "--iterations", "60", "--max-iter", "1"]
    assert _cli([*args, "--out", str(tmp_path / "single")]) == 0, capsys.readouterr().err
    assert _cli([*args, "--out", str(tmp_path / "dask"), "--scheduler", client.scheduler.address]) == 0, \
        capsys.readouterr().err
    assert "[2/2]" in capsys.readouterr().err
    single = json.loads((tmp_path / "single" / "report.json").read_text())
    dask = json.loads((tmp_path / "dask" / "report.json").read_text())
    assert single == dask  # the report holds no timing field
    assert single["diagnostic"]["findings"][0]["variable"] == "field_pass"
    assert (tmp_path / "single" / "report.md").read_text() == (tmp_path / "dask" / "report.md").read_text()
