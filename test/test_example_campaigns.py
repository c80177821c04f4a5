"""The example campaign files shipped in config/campaigns load and pass the data checks of `xmetro calibrate`
(issue 27: the schema's example is a file a user can copy, not only a docstring)."""

from __future__ import annotations

from pathlib import Path

from conftest import need_shared

from xmetro_ros.calibrate.campaign_data import assemble
from xmetro_ros.calibrate.campaign_file import load_campaign
from xmetro_ros.calibrate.profile_campaign import PROFILE_CAMPAIGN_FORMAT, campaign_format, load_profile_campaign

ROOT = Path(__file__).resolve().parents[1]
CAMPAIGNS = ROOT / "config" / "campaigns"


def test_demo_campaign_passes_the_data_checks():
    from xmetro_ros.ros.scan_io import read_scans

    camp = load_campaign(CAMPAIGNS / "demo_campaign.yaml")
    assert camp.scanner_id == "xm-ls90" and sorted(camp.artifacts) == ["ball_35", "ball_45", "ball_55"]
    data = assemble(camp, lambda rec: read_scans(rec.bag, topic=rec.scan_topic, settings_topic=rec.settings_topic,
                                                 scanner=camp.scanner), require_levels=False)
    assert [it.placement.artifact for it in data.scans] == ["ball_35", "ball_45", "ball_55"]
    assert [it.placement.fitted for it in data.scans] == [False, True, True]
    assert data.checks.n_measurements == 3


def test_profile_campaign_loads():
    f = CAMPAIGNS / "profiler_r19.yaml"
    assert campaign_format(f) == PROFILE_CAMPAIGN_FORMAT
    need_shared(ROOT.parent / "shared" / "data" / "measured" / "profiler_sphere_r19_labelled" / "train_file.txt")
    camp = load_profile_campaign(f)
    assert camp.artifact.radius_mm == 19.05 and camp.lists[0].list_file.name == "train_file.txt"
    assert camp.border_angle_deg == 66.0
