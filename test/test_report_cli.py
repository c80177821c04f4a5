"""`xmetro report BAG`: the demo's report for any judged bag (issue 27) — here `xmetro predict`'s output of the
shipped demo bag: U and the decisions in the table, one usable figure equal to ScanQuality's, deviation and U
maps; a bag without judged scans is an error that says what to run."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from xmetro_ros.apps.cli import main
from xmetro_ros.ros.node_outputs import read_outputs

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def judged_report(tmp_path_factory):
    """`xmetro predict` of the shipped demo bag and `xmetro report` of its output: (judged bag, report)."""
    tmp = tmp_path_factory.mktemp("report")
    judged = tmp / "judged.mcap"
    assert main(["predict", str(ROOT / "bags" / "demo.mcap"), "--out", str(judged), "--deterministic"]) == 0
    assert main(["report", str(judged), "--out", str(tmp / "r.html")]) == 0
    return judged, tmp / "r.html"


def test_report_of_a_predicted_bag(judged_report, tmp_path, capsys):
    judged, report = judged_report
    html = report.read_text()
    assert "<h1>xmetro report: judged.mcap</h1>" in html and "p95 U x/y/z [µm]" in html
    assert len(re.findall(r"alt='deviation map \d'", html)) == 4 and len(re.findall(r"alt='uncertainty map \d'",
                                                                                      html)) == 4
    for o in read_outputs(judged):
        q = o.quality
        assert f"<td>{q.usable_fraction:.3f}</td>" in html
        u = " / ".join(f"{v * 1e6:.2f}" for v in q.p95_uncertainty)
        assert f"<td>{u}</td>" in html
    assert "lat6_dir3_exp2" in html  # the input scans' settings: predict keeps the inputs (not their metadata)
    assert "xmetro demo --bag" in html  # what the services sections say in a recorded bag
    capsys.readouterr()
    assert main(["report", str(ROOT / "bags" / "demo.mcap"), "--out", str(tmp_path / "x.html")]) == 2
    err = capsys.readouterr().err
    assert "holds no /xmetro_node/quality" in err and "xmetro predict" in err
    assert not (tmp_path / "x.html").exists()
    assert main(["report", str(judged), "--out", str(tmp_path / "t.html"), "--tolerance", "-1"]) == 2
    assert "--tolerance must be a positive length" in capsys.readouterr().err


def test_report_in_a_browser(judged_report, tmp_path):
    """Issue 27: headless chromium renders `xmetro report`'s page with no console error and every figure loaded;
    it carries U, the tolerance behind the decisions, each scan's settings as judged and ScanQuality's usable
    figure (read back from the judged bag); a node run with another tolerance is stated with --tolerance."""
    from report_browser import check_report

    from xmetro_ros.apps.demo import _node_tolerance_m

    judged, report = judged_report
    outputs = read_outputs(judged)
    r = check_report(report, outputs, tolerance_um=_node_tolerance_m() * 1e6, recommendation=None)
    assert "the node's default tolerance: a bag does not record the node's parameters" in r.text
    assert main(["report", str(judged), "--out", str(tmp_path / "t.html"), "--tolerance", "0.00025"]) == 0
    html = (tmp_path / "t.html").read_text()
    assert "against the tolerance 250.0 µm (<code>xmetro report --tolerance</code>)" in html
