"""`xmetro report BAG`: the demo's report for any judged bag (issue 27) — here `xmetro predict`'s output of the
shipped demo bag: U and the decisions in the table, one usable figure equal to ScanQuality's, deviation and U
maps; a bag without judged scans is an error that says what to run."""

from __future__ import annotations

import re
from pathlib import Path

from xmetro_ros.apps.cli import main
from xmetro_ros.ros.node_outputs import read_outputs

ROOT = Path(__file__).resolve().parents[1]


def test_report_of_a_predicted_bag(tmp_path, capsys):
    judged = tmp_path / "judged.mcap"
    assert main(["predict", str(ROOT / "bags" / "demo.mcap"), "--out", str(judged), "--deterministic"]) == 0
    assert main(["report", str(judged), "--out", str(tmp_path / "r.html")]) == 0
    html = (tmp_path / "r.html").read_text()
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
