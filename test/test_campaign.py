"""Calibration campaign file and its assembly (ROS-free): the simulator plays a foreign scanner; every campaign
error names the scan and the cause; fitted centres, ball bars and VDI/VDE 2634-2 figures against the truth."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from xmetro_ros.calibrate.campaign_data import assemble
from xmetro_ros.calibrate.campaign_file import CampaignError, load_campaign
from xmetro_ros.calibrate.vdi2634 import probing, summarize
from xmetro_ros.scan.artifacts import Sphere
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim import simulate_scan

RANGES = {"lateral_density": [0.5, 100], "direction_density": [0.1, 50], "exposure_ms": [0.005, 50]}
SHEET = {"id": "ls-200", "serial": "SN-7", "measuring_range_mm": [150.0, 250.0], "field_of_view_mm": [100.0, 180.0],
         "triangulation_angle_deg": 20.0, "camera_side": "+y", "settings_range": RANGES,
         "default_settings": {"lateral_density": 4.0, "direction_density": 2.0, "exposure_ms": 0.5}}
CENTRES = {"ball_a": (30.0, -8.0, 0.0), "ball_b": (-32.0, 6.0, 2.0)}
RADIUS = 12.7


@pytest.fixture(scope="module")
def scanner() -> ScannerModel:
    return ScannerModel.from_dict({**SHEET, "effects": ScannerModel.load().effects}, "sheet")


def _scans(scanner: ScannerModel, n: int = 2, seed: int = 0) -> list:
    """Scans each showing both balls (the union of two simulated spheres, as one cloud)."""
    out = []
    for k in range(n):
        s = ScanSettings((4.0, 6.0)[k % 2], (2.0, 3.0)[k % 2], (0.5, 2.0)[k % 2])
        a = simulate_scan(Sphere(RADIUS, CENTRES["ball_a"]), s, scanner=scanner, seed=seed + 2 * k)
        b = simulate_scan(Sphere(RADIUS, CENTRES["ball_b"]), s, scanner=scanner, seed=seed + 2 * k + 1)
        pts = np.concatenate([a.points.reshape(-1, 3), b.points.reshape(-1, 3)])
        out.append(replace(a, points=pts, artifact=None, expected_error=None, noise_std=None, injected_outlier=None,
                           fields={}, stamp_ns=(k + 1) * 10**9, meta={}))
    return out


def _write(tmp: Path, placements_a: dict, placements_b: dict | None = None, sheet_levels: dict | None = None,
           **over: object) -> Path:
    sheet = {**SHEET, "effects": ScannerModel.load().effects}
    if sheet_levels is not None:
        sheet["settings_levels"] = sheet_levels
    (tmp / "ls-200.yaml").write_text(yaml.safe_dump(sheet))
    (tmp / "run1.mcap").write_bytes(b"")
    places = [{"artifact": "ball_a", **placements_a}]
    if placements_b is not None:
        places.append({"artifact": "ball_b", **placements_b})
    d = {"format": "xmetro-campaign/1", "scanner": {"id": "ls-200", "serial": "SN-7", "description": "ls-200.yaml"},
         "artifacts": [{"id": "ball_a", "kind": "sphere", "diameter_mm": 2 * RADIUS, "certificate": "C-1"},
                       {"id": "ball_b", "kind": "sphere", "diameter_mm": 2 * RADIUS, "certificate": "C-2"},
                       {"id": "bar", "kind": "ball_bar", "spheres": ["ball_a", "ball_b"],
                        "distance_mm": float(np.linalg.norm(np.subtract(CENTRES["ball_a"], CENTRES["ball_b"])))}],
         "recordings": [{"bag": "run1.mcap", "placements": places}]}
    d.update(over)
    p = tmp / "campaign.yaml"
    p.write_text(yaml.safe_dump(d, sort_keys=False))
    return p


def test_known_and_fitted_positions(tmp_path, scanner):
    scans = _scans(scanner)
    path = _write(tmp_path, {"position": {"known": list(CENTRES["ball_a"]), "uncertainty_mm": 0.002,
                                          "source": "CMM"}},
                  {"position": {"fit": [-31.0, 5.0, 1.0]}})
    camp = load_campaign(path)
    assert camp.scanner.id == "ls-200" and camp.scanner_serial == "SN-7" and len(camp.sha256) == 64
    data = assemble(camp, lambda rec: scans)
    assert data.checks.n_measurements == 4 and data.checks.per_artifact == {"ball_a": 2, "ball_b": 2}
    assert data.checks.levels_from_campaign and data.scanner.settings_levels["exposure_ms"] == (0.5, 2.0)
    for it in data.scans:
        art = it.scan.artifact
        assert isinstance(art, Sphere) and art.radius == RADIUS
        if it.placement.artifact == "ball_a":  # known: exactly the declared centre
            assert art.center == CENTRES["ball_a"] and it.fitted_center is None
        else:  # fitted with the certified radius (then the ball bar): near the truth, but it absorbs the scanner's
            # errors that look like a shift of the sphere (tens of µm here): what a fitted position costs
            off = np.linalg.norm(np.subtract(art.center, CENTRES["ball_b"]))
            assert 0 < off < 0.1
        # each view holds only its own sphere's points
        p = it.scan.points[np.isfinite(it.scan.points).all(axis=-1)]
        d = np.abs(np.linalg.norm(p - np.asarray(CENTRES[it.placement.artifact]), axis=1) - RADIUS)
        assert np.percentile(d, 99) < 0.5
        # VDI/VDE 2634-2 figures of the simulated scanner: size error tens of µm at most, form error > 0
        assert abs(it.figures.size_error_mm) < 0.15 and 0 < it.figures.form_error_mm < 2.0
    assert len(data.spacing) == 2 and all(abs(r["SD_mm"]) < 0.15 for r in data.spacing)
    assert set(summarize(data.spacing)) == {s.settings.label() for s in scans}


def test_ball_bar_constrains_fitted_centres(tmp_path, scanner):
    scans = _scans(scanner, n=1)
    path = _write(tmp_path, {"position": {"fit": [29.0, -7.0, 0.5]}}, {"position": {"fit": [-31.0, 5.0, 1.0]}})
    data = assemble(load_campaign(path), lambda rec: scans)
    a, b = sorted(data.scans, key=lambda it: it.placement.artifact)
    bar = load_campaign(path).ball_bars[0].distance_mm
    assert np.linalg.norm(np.subtract(a.fitted_center, b.fitted_center)) == pytest.approx(bar, abs=1e-9)


def test_probing_figures_against_a_known_sphere():
    rng = np.random.default_rng(0)
    u = rng.normal(size=(5000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    pts = np.array([1.0, 2.0, 3.0]) + 10.01 * u  # a sphere 20 µm too large in diameter, perfect form
    f = probing(pts, 20.0, known_center=(1.0, 2.0, 3.0))
    assert f.size_error_mm == pytest.approx(0.02, abs=1e-9) and f.form_error_mm < 1e-9
    assert f.location_error_mm < 1e-9


@pytest.mark.parametrize("mutate, match", [
    (lambda d: d["recordings"][0]["placements"].append({"artifact": "ball_z", "position": {"fit": [0, 0, 0]}}),
     r"unknown artifact 'ball_z'"),
    (lambda d: d["artifacts"][0].pop("diameter_mm"), "certified diameter_mm or radius_mm"),
    (lambda d: d["recordings"][0].update(bag="nope.mcap"), r"bag .*nope.mcap does not exist"),
    (lambda d: d["scanner"].update(id="other"), "differs from its description's id"),
    (lambda d: d["recordings"][0]["placements"][0].update(position={"known": [1, 2]}), "three numbers"),
    (lambda d: d.update(format="v0"), "format must be"),
])
def test_campaign_file_errors_name_the_entry(tmp_path, mutate, match):
    path = _write(tmp_path, {"position": {"fit": [30, -8, 0]}}, {"position": {"fit": [-32, 6, 2]}})
    d = yaml.safe_load(path.read_text())
    mutate(d)
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(CampaignError, match=match):
        load_campaign(path)


def test_data_errors_name_the_scan_and_the_cause(tmp_path, scanner):
    scans = _scans(scanner, n=1)
    ok = {"position": {"fit": [30, -8, 0]}}, {"position": {"fit": [-32, 6, 2]}}
    camp = load_campaign(_write(tmp_path, *ok))
    # an artifact placed where nothing is: not found, the scan named
    far = load_campaign(_write(tmp_path, ok[0], {"position": {"known": [0.0, 80.0, 0.0]}}))
    with pytest.raises(CampaignError, match=r"recording 0 .* scan 0 .*artifact 'ball_b' not found"):
        assemble(far, lambda rec: scans)
    # a radius that does not fit the certificate
    small = yaml.safe_load(_write(tmp_path, *ok).read_text())
    small["artifacts"][1]["diameter_mm"] = 2 * RADIUS - 3.0
    (tmp_path / "campaign.yaml").write_text(yaml.safe_dump(small))
    with pytest.raises(CampaignError, match=r"scan 0 .*'ball_b'.*certified radius"):
        assemble(load_campaign(tmp_path / "campaign.yaml"), lambda rec: scans)
    # scans of another scanner, scans without settings
    with pytest.raises(CampaignError, match=r"scan 0 .*scanner 'xm-ls90'"):
        assemble(camp, lambda rec: [replace(scans[0], scanner_id="xm-ls90")])
    with pytest.raises(CampaignError, match=r"scan 0 .*no ScannerSettings"):
        assemble(camp, lambda rec: [replace(scans[0], meta={"settings_defaulted": True})])


def test_single_profile_data_are_refused_with_the_reason(tmp_path, scanner):
    """The AT C5 case: one laser profile per pose gives no surface normals."""
    scan = _scans(scanner, n=1)[0]
    p = scan.points.reshape(-1, 3)
    prof = p[np.isfinite(p).all(axis=1) & (np.abs(p[:, 1] - 0.0) < 0.3)].copy()
    prof[:, 1] = 0.0
    one = replace(scan, points=prof)
    camp = load_campaign(_write(tmp_path, {"position": {"fit": [30, -8, 0]}}, {"position": {"fit": [-32, 6, 2]}}))
    with pytest.raises(CampaignError, match=r"scan 0 .*single laser profile"):
        assemble(camp, lambda rec: [one])


def test_the_real_atc5_profiles_are_refused_with_the_reason(tmp_path, scanner):
    """The measured AT C5 set (../shared/data): 15 single laser profiles of a 40 mm sphere. A calibration campaign
    built on them is refused, scan by scan, because a profile gives no surface normals."""
    from conftest import need_shared, shared_data

    from xmetro_ros.scan.geometry import HeadPose
    from xmetro_ros.scan.measured import load_atc5
    from xmetro_ros.scan.scan import Scan

    profiles = load_atc5(need_shared(shared_data() / "measured" / "atc5_profiler_sphere_r40"))
    xz = profiles[0].xz
    pts = np.c_[xz[:, 0], np.zeros(len(xz)), xz[:, 1]]
    scan = Scan(points=pts, settings=ScanSettings(4.0, 2.0, 0.5), pose=HeadPose.looking_down(175.0),
                scanner_id="ls-200", stamp_ns=10**9)
    camp = load_campaign(_write(tmp_path, {"position": {"fit": [0, 0, 0]}}, {"position": {"fit": [0, 0, 0]}}))
    with pytest.raises(CampaignError, match=r"recording 0 .*scan 0 .*single laser profile.*cannot be estimated"):
        assemble(camp, lambda rec: [scan])


@pytest.mark.parametrize("scans_b, match", [
    ({"indices": [1, 5]}, r"recording 0 \(run1.mcap\) \(2 scans on /scan\): placement of artifact 'ball_b' "
                          r"\(indices \[1, 5\]\): indices \[5\] match no scan \(the recording has 2 scans"),
    ({"stamps_ns": [10**9, 7 * 10**9]}, r"recording 0 \(run1.mcap\).*'ball_b' .*stamps_ns \[7000000000\] match no "
                                        r"scan header stamp"),
    ({"from_s": 50.0}, r"recording 0 \(run1.mcap\).*'ball_b' .*window from_s 50.0 to_s None selects no scan"),
])
def test_listed_scans_missing_from_the_recording_are_errors(tmp_path, scanner, scans_b, match):
    """A stamp / index the campaign lists but the bag does not hold is an error naming the recording, the
    artifact and what is missing (never silently skipped)."""
    scans = _scans(scanner)
    camp = load_campaign(_write(tmp_path, {"position": {"fit": [30, -8, 0]}},
                                {"position": {"fit": [-32, 6, 2]}, "scans": scans_b}))
    with pytest.raises(CampaignError, match=match):
        assemble(camp, lambda rec: scans)


def test_listed_scans_select_them(tmp_path, scanner):
    scans = _scans(scanner)
    for sel in ({"indices": [1]}, {"stamps_ns": [2 * 10**9]}, {"from_s": 0.5}):
        camp = load_campaign(_write(tmp_path, {"position": {"fit": [30, -8, 0]}},
                                    {"position": {"fit": [-32, 6, 2]}, "scans": sel}))
        data = assemble(camp, lambda rec: scans, check_normals=False)
        assert data.checks.per_artifact == {"ball_a": 2, "ball_b": 1}, sel
        assert [it.index for it in data.scans if it.placement.artifact == "ball_b"] == [1]


LEVELS = {"lateral_density": [4.0, 6.0], "direction_density": [2.0, 3.0], "exposure_ms": [0.5, 2.0]}


def test_declared_settings_levels_must_be_scanned(tmp_path, scanner):
    """Levels the scanner description (or the campaign file) declares are the model's promise: one no scan shows
    stops the run, naming it. Levels derived from the scans are covered by construction (a note only)."""
    scans = _scans(scanner)  # settings (4, 2, 0.5) and (6, 3, 2)
    fit = {"position": {"fit": [30, -8, 0]}}, {"position": {"fit": [-32, 6, 2]}}
    wide = {**LEVELS, "lateral_density": [4.0, 6.0, 8.0]}
    camp = load_campaign(_write(tmp_path, *fit, sheet_levels=wide))
    with pytest.raises(CampaignError, match=r"settings levels declared by the scanner description .*ls-200.yaml are "
                                            r"in no scan: lateral_density = 8 "):
        assemble(camp, lambda rec: scans, check_normals=False)
    # described levels all scanned: checked, kept
    data = assemble(load_campaign(_write(tmp_path, *fit, sheet_levels=LEVELS)), lambda rec: scans,
                    check_normals=False)
    assert data.checks.levels_source == "scanner description" and not data.checks.levels_from_campaign
    # the campaign file declares the levels it covers: they are checked and become the model's (over the
    # description's wider grid)
    data = assemble(load_campaign(_write(tmp_path, *fit, sheet_levels=wide, settings_levels=LEVELS)),
                    lambda rec: scans, check_normals=False)
    assert data.checks.levels_source == "campaign file" and data.scanner.settings_levels["lateral_density"] == (4, 6)
    over = load_campaign(_write(tmp_path, *fit, settings_levels={**LEVELS, "exposure_ms": [0.5, 1.0, 2.0]}))
    with pytest.raises(CampaignError, match=r"declared by the campaign campaign.yaml are in no scan: exposure_ms = 1 "):
        assemble(over, lambda rec: scans, check_normals=False)
    # nothing declared: the scans' levels are used, with a note
    data = assemble(load_campaign(_write(tmp_path, *fit)), lambda rec: scans, check_normals=False)
    assert data.checks.levels_source == "scans" and any("campaign's are used" in n for n in data.checks.notes)
    with pytest.raises(CampaignError, match=r"settings_levels must give the levels of each of"):
        load_campaign(_write(tmp_path, *fit, settings_levels={"exposure_ms": [0.5]}))
