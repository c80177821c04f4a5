"""Virtual scanner: organized output, geometry (occlusion, depth of field), each effect's law, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from xmetro_ros.scan.artifacts import ArtifactSpecError, Cylinder, Plane, Sphere
from xmetro_ros.scan.geometry import HeadPose
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings, SettingsError
from xmetro_ros.sim import EFFECTS, EffectConfigError, UnknownEffectError, simulate_scan

SC = ScannerModel.load()
DEF = SC.default_settings


def only(*names: str, **params: dict) -> dict:
    """Effects config with only ``names`` enabled (plus per-effect parameter overrides)."""
    cfg = {n: {"enabled": n in names} for n in EFFECTS}
    for n, p in params.items():
        cfg[n].update(p)
    return cfg


NONE = only()


def tilted_plane(axis: str, deg: float, z: float = 0.0) -> Plane:
    a = np.radians(deg)
    n = (np.sin(a), 0.0, np.cos(a)) if axis == "y" else (0.0, np.sin(a), np.cos(a))
    return Plane((0.0, 0.0, z), n)


def kept(scan):
    v = scan.valid_mask()
    return scan.points.reshape(-1, 3)[v], scan.expected_error.reshape(-1, 3)[v], v


def test_organized_output_fields_and_meta():
    scan = simulate_scan(Sphere(17.5), DEF, scanner=SC, seed=3)
    h, w = scan.shape
    assert scan.organized and scan.points.shape == (h, w, 3) and h > 50 and w > 100
    assert set(scan.fields) == {"intensity", "line", "t", "u"}
    v = scan.valid_mask()
    for name, arr in scan.fields.items():
        assert arr.dtype == np.float32 and arr.shape == (h, w)
        assert np.all(np.isfinite(arr.reshape(-1)[v])) and np.all(np.isnan(arr.reshape(-1)[~v])), name
    assert np.all(np.isnan(scan.expected_error.reshape(-1, 3)[~v]))
    inten = scan.fields["intensity"].reshape(-1)[v]
    assert inten.min() >= 0 and inten.max() <= 1
    # line = profile index, t = line * period (0.5 ms at 2 kHz, 0.5 ms exposure), u = head X of the point.
    rows = np.repeat(np.arange(h), w)[v]
    assert np.array_equal(scan.fields["line"].reshape(-1)[v], rows.astype(np.float32))
    assert np.allclose(scan.fields["t"].reshape(-1)[v], rows * 0.5e-3, rtol=1e-5)
    pts = scan.points.reshape(-1, 3)[v]
    assert np.allclose(scan.fields["u"].reshape(-1)[v], scan.pose.to_head(pts)[:, 0], atol=1e-4)
    # Profiles are 1/direction_density apart along +Y; points within a profile ~1/lateral_density apart.
    assert np.allclose(np.diff(scan.pose.to_world(np.c_[np.zeros(2), [0, 0.25], np.zeros(2)])[:, 1]), 0.25)
    m = scan.meta
    assert m["seed"] == 3 and m["scanner"] == SC.id and m["artifact"] == Sphere(17.5).to_dict()
    assert list(m["effects"]) == list(EFFECTS) and m["effects"]["incidence"]["exponent"] == 1.4
    json.dumps(m)
    assert m["n_points"] == scan.n_valid


def test_seed_reproducible_and_effects_recorded():
    a = simulate_scan(Sphere(10), DEF, scanner=SC, seed=5)
    b = simulate_scan(Sphere(10), DEF, scanner=SC, seed=5)
    c = simulate_scan(Sphere(10), DEF, scanner=SC, seed=6)
    assert np.array_equal(a.points, b.points, equal_nan=True)
    assert not np.array_equal(a.points, c.points, equal_nan=True)
    # Systematic part does not depend on the seed (only outlier-free geometry does).
    both = a.valid_mask() & c.valid_mask()
    assert np.allclose(a.expected_error.reshape(-1, 3)[both], c.expected_error.reshape(-1, 3)[both])
    d = simulate_scan(Sphere(10), DEF, scanner=SC, seed=5, effects={"speckle": {"enabled": False}})
    assert "speckle" not in d.meta["effects"] and "incidence" in d.meta["effects"]
    e = simulate_scan(Sphere(10), DEF, scanner=SC, seed=5, effects={"speckle": {"sigma_mm": 0.001}})
    assert e.meta["effects"]["speckle"]["sigma_mm"] == 0.001


def test_noise_free_points_lie_on_the_artifact_and_camera_sees_them():
    for art in (Sphere(20), Cylinder(15), Plane()):
        scan = simulate_scan(art, DEF, scanner=SC, effects=NONE)
        pts, exp, v = kept(scan)
        assert len(pts) > 1000
        assert np.abs(art.errors(pts)).max() < 1e-9 and np.abs(exp).max() < 1e-9
    # Camera occlusion: every point faces the camera of its profile; the -Y flank of a sphere is hidden.
    scan = simulate_scan(Sphere(20), DEF, scanner=SC, effects=NONE)
    pts, _, v = kept(scan)
    rows = np.repeat(np.arange(scan.shape[0]), scan.shape[1])[v]
    zero = np.zeros(len(rows))
    cam = scan.pose.to_world(np.c_[zero, rows / DEF.direction_density + SC.baseline_mm, zero])
    n = Sphere(20).normals(pts)
    assert np.all(np.einsum("ij,ij->i", n, cam - pts) > 0)
    assert pts[:, 1].min() > -19.0 and pts[:, 1].max() > 19.5  # the +Y side (toward the camera) is seen to its rim


def test_depth_of_field_drops_points():
    # A plane 50 mm above the centre sits at 40 mm stand-off: outside [55, 125] → nothing returns.
    assert simulate_scan(Plane((0, 0, 50.0)), DEF, scanner=SC, effects=NONE).n_valid > 0
    assert simulate_scan(Plane((0, 0, 50.0)), DEF, scanner=SC, effects=only("depth_of_field")).n_valid == 0
    scan = simulate_scan(Sphere(40, (0, 0, -10)), DEF, scanner=SC, effects=only("depth_of_field"))
    pts, _, _ = kept(scan)
    r = 90.0 - pts[:, 2]
    assert r.min() >= 55.0 and r.max() <= 125.0 and scan.n_valid > 1000


def test_incidence_noise_follows_its_law():
    p = EFFECTS["incidence"]().params
    sig = []
    for deg in (0.0, 45.0, 65.0):
        art = tilted_plane("y", deg)
        scan = simulate_scan(art, DEF, scanner=SC, effects=only("incidence"), seed=1, extent_mm=10)
        pts, _, _ = kept(scan)
        ne = art.normal_error(pts)
        # Depth noise sigma * cos^-p * cos_view^-pv along the ray; seen along the normal it is x cos(inc).
        g = scan.pose.to_head(pts)
        d = np.c_[g[:, 0], np.zeros(len(g)), g[:, 2]]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        ci = np.abs(d @ art.n)
        v = np.c_[-g[:, 0], np.full(len(g), SC.baseline_mm), -g[:, 2]]
        cv = (v / np.linalg.norm(v, axis=1, keepdims=True)) @ art.n
        expect = p["sigma_mm"] * ci ** (1 - p["exponent"]) * cv ** (-p["view_exponent"])
        z = ne / expect
        assert abs(z.mean()) < 0.05 and 0.93 < z.std() < 1.07, (deg, z.std())
        sig.append(ne.std())
    assert sig[0] < sig[1] < sig[2]


def test_centroid_bias_sign_and_size():
    # Normal error (positive = measured inside) = depth bias * cos(inc) = coefficient * N_y (unclipped).
    c = EFFECTS["centroid"]().params["coefficient_mm"]
    for deg in (-40.0, 40.0):
        art = tilted_plane("x", deg)
        scan = simulate_scan(art, DEF, scanner=SC, effects=only("centroid"), extent_mm=10)
        _pts, exp, _ = kept(scan)
        ne = np.einsum("ij,j->i", exp, art.n)
        assert np.allclose(ne, c * art.n[1], rtol=0.02, atol=2e-5)
    # Capped at max_mm (0.1 mm depth) even at grazing tilt.
    law = EFFECTS["centroid"]()
    assert law.bias(np.array([1e6, -1e6])).tolist() == [0.1, -0.1]


def test_standoff_bias_law_drives_z():
    eff = EFFECTS["standoff"]()
    for z in (-25.0, 25.0):
        art = Plane((0, 0, z))
        scan = simulate_scan(art, DEF, scanner=SC, effects=only("standoff"), extent_mm=6)
        pts, exp, _ = kept(scan)
        zeta = ((90.0 - z) - 90.0) / 35.0
        # Near the fan centre the ray is ~vertical: Z error = -bias (measured farther = lower = positive error).
        centre = np.abs(pts[:, 0]) < 1
        assert np.allclose(exp[centre, 2], eff.bias(np.array([zeta]))[0], rtol=0.01)
        assert np.abs(exp[:, :2]).max() < 0.2 * np.abs(exp[:, 2]).max()


def test_exposure_saturation_bias_and_short_exposure_noise():
    art = Plane()
    lo, hi = (ScanSettings(10, 4, e) for e in (0.5, 2.0))
    s_lo = simulate_scan(art, lo, scanner=SC, effects=only("exposure"), extent_mm=6)
    s_hi = simulate_scan(art, hi, scanner=SC, effects=only("exposure"), extent_mm=6)
    assert np.abs(kept(s_lo)[1]).max() < 1e-12  # amplitude 1 < 1.5: not saturated
    pts, exp, v = kept(s_hi)
    centre = np.abs(pts[:, 0]) < 1
    # A = 4 * cos(inc) ~ 4 → bias 0.006 * ln(4 / 1.5) measured farther (below): positive Z error.
    assert np.allclose(exp[centre, 2], 0.006 * np.log(4 / 1.5), rtol=0.01)
    assert s_hi.fields["intensity"].reshape(-1)[v].min() == 1.0
    # Short exposure: shot noise x sqrt(T_ref / T) on the SNR-limited noise (incidence law).
    sd = []
    for e in (0.1, 0.5):
        sc = simulate_scan(art, ScanSettings(10, 4, e), scanner=SC, effects=only("exposure", "incidence"), seed=2,
                           extent_mm=10)
        sd.append(art.normal_error(kept(sc)[0]).std())
    assert sd[0] / sd[1] == pytest.approx(np.sqrt(5.0), rel=0.08)


def test_speckle_is_spatially_correlated():
    art = Plane()
    res = {}
    for name in ("speckle", "incidence"):
        scan = simulate_scan(art, DEF, scanner=SC, effects=only(name), seed=4, extent_mm=20)
        grid = art.normal_error(np.nan_to_num(scan.points.reshape(-1, 3))).reshape(scan.shape)
        grid[~scan.valid_mask().reshape(scan.shape)] = np.nan
        a, b = grid[:, :-1].ravel(), grid[:, 1:].ravel()
        ok = np.isfinite(a) & np.isfinite(b)
        along = np.corrcoef(a[ok], b[ok])[0, 1]
        a, b = grid[:-1].ravel(), grid[1:].ravel()
        ok = np.isfinite(a) & np.isfinite(b)
        res[name] = (along, np.corrcoef(a[ok], b[ok])[0, 1], np.nanstd(grid))
    # Gaussian correlation, sigma 3 px along (0.3 mm x 10 /mm) and 2.4 px across: neighbour correlation ~0.95.
    assert res["speckle"][0] > 0.85 and res["speckle"][1] > 0.8
    assert abs(res["incidence"][0]) < 0.1 and abs(res["incidence"][1]) < 0.1
    assert res["speckle"][2] == pytest.approx(0.005 / np.sqrt(1 + 0.25 / 0.5), rel=0.25)


def test_edge_effect_pushes_horizon_points_outward():
    art = Sphere(20)
    scan = simulate_scan(art, DEF, scanner=SC, effects=only("edge"))
    pts, exp, _ = kept(scan)
    ne = np.einsum("ij,ij->i", exp, art.normals(pts))
    g = scan.pose.to_head(pts)
    d = np.c_[g[:, 0], np.zeros(len(g)), g[:, 2]]
    inc = np.degrees(np.arccos(np.abs(np.einsum("ij,ij->i", d / np.linalg.norm(d, axis=1)[:, None],
                                                art.normals(pts)))))
    assert np.all(ne <= 1e-12) and ne.min() < -0.01 and ne.min() >= -0.04
    assert np.abs(ne[inc < 50]).max() < 2e-4  # local to the horizon
    grazing = inc > 80
    assert np.abs(exp[grazing, 0]).mean() > np.abs(exp[grazing, 1]).mean()  # drives X at the line ends


def test_anisotropy_drives_x_not_y():
    art = Sphere(20)
    scan = simulate_scan(art, DEF, scanner=SC, effects=only("anisotropy"), keep_context=True)
    _, exp, _ = kept(scan)
    mx, my = np.abs(exp[:, :2]).mean(axis=0)
    assert mx > 1.8 * my  # radial projection puts some of a lateral shift on Y where N_y is large
    ctx = scan.meta["_context"]
    disp = ctx.contributions["anisotropy"]
    assert np.abs(disp[:, 1]).max() < 1e-15 and np.abs(disp[:, 0]).mean() > 1e-3  # no displacement along the scan
    assert np.abs(ctx.noise_contributions["anisotropy"][:, 1]).max() < 1e-15
    law = EFFECTS["anisotropy"]()
    assert law.tilt_bias(np.array([0.5]))[0] == pytest.approx(0.01)


def test_motion_blur_grows_with_speed_times_exposure():
    art = tilted_plane("x", 30.0)
    shifts = []
    for dd, exp_ms in ((5, 0.1), (3, 2.0)):
        scan = simulate_scan(art, ScanSettings(10, dd, exp_ms), scanner=SC, effects=only("motion_blur"), extent_mm=8)
        _, e, _ = kept(scan)
        b = scan.meta["blur_mm"]
        # period = max(0.5 ms, T); speed = 1 / (dd * period); blur = speed * T.
        assert b == pytest.approx(exp_ms * 1e-3 / (dd * max(0.5e-3, exp_ms * 1e-3)))
        ne = np.einsum("ij,j->i", e, art.n)
        # Stamp lag shifts points by -0.03 b along Y: normal error = +0.03 b N_y (plane: no curvature term).
        assert np.allclose(ne, 0.03 * b * art.n[1], rtol=0.02, atol=1e-7)
        shifts.append(np.abs(ne).mean())
    assert shifts[1] > 5 * shifts[0]


def test_outliers_fraction_and_size():
    art = Plane()
    scan = simulate_scan(art, DEF, scanner=SC, effects=only("outliers", outliers={"fraction": 0.01}), extent_mm=30)
    ne = np.abs(art.normal_error(kept(scan)[0]))
    out = ne > 0.1
    assert 0.007 < out.mean() < 0.016
    assert ne[out].min() > 0.15 and ne[out].max() <= 1.5
    assert scan.meta["n_outliers"] == out.sum()
    assert np.abs(kept(scan)[1]).max() < 1e-12  # spurious returns are random: not in expected_error


def test_every_effect_documented_and_configurable():
    for name, cls in EFFECTS.items():
        assert cls.name == name and cls.law and cls.source and cls.magnitude and cls.drives
        assert SC.effects[name]["enabled"] is True
        assert {k: v for k, v in SC.effects[name].items() if k != "enabled"} == cls.defaults


def test_bad_input_raises_specific_errors():
    with pytest.raises(UnknownEffectError, match="warp"):
        simulate_scan(Sphere(10), DEF, scanner=SC, effects={"warp": {"enabled": True}})
    with pytest.raises(EffectConfigError, match="sigmaa"):
        simulate_scan(Sphere(10), DEF, scanner=SC, effects={"speckle": {"sigmaa": 1}})
    with pytest.raises(EffectConfigError, match="sigma_mm"):
        simulate_scan(Sphere(10), DEF, scanner=SC, effects={"incidence": {"sigma_mm": -1}})
    with pytest.raises(EffectConfigError, match="finite"):
        simulate_scan(Sphere(10), DEF, scanner=SC, effects={"speckle": {"sigma_mm": "big"}})
    with pytest.raises(EffectConfigError, match="enabled"):
        simulate_scan(Sphere(10), DEF, scanner=SC, effects={"speckle": {"enabled": "yes"}})
    with pytest.raises(ArtifactSpecError, match="unknown artifact type"):
        simulate_scan("sphere", DEF, scanner=SC)
    with pytest.raises(ArtifactSpecError, match="positive"):
        simulate_scan(Sphere(-3), DEF, scanner=SC)
    with pytest.raises(SettingsError, match="lateral_density"):
        simulate_scan(Sphere(10), ScanSettings(0.0, 4, 0.5), scanner=SC)
    with pytest.raises(SettingsError, match="exposure_ms"):
        simulate_scan(Sphere(10), ScanSettings(10, 4, 500.0), scanner=SC)
    with pytest.raises(ValueError, match="extent_mm"):
        simulate_scan(Cylinder(10), DEF, scanner=SC, extent_mm=0)
    with pytest.raises(ValueError, match="behind"):
        simulate_scan(Sphere(10), DEF, scanner=SC, pose=HeadPose.looking_down(90, y_mm=50))
