"""The mean curvature of a scanned surface (preprocess/curvature.py) against the simulator's known shapes, and the
shape part of the model's domain built from it (learn/shape_domain.py, card ``domain_shape``)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from xmetro_ros.judge.inference import ModelSet
from xmetro_ros.judge.scan_handler import ScanHandler
from xmetro_ros.preprocess import prepare_scan
from xmetro_ros.preprocess.curvature import grid_mean_curvature, mean_curvature
from xmetro_ros.scan.artifacts import Cylinder, Plane, Sphere
from xmetro_ros.scan.resources import default_model_dir
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim import simulate_scan

SC = ScannerModel.load()


DEFAULT = ScanSettings(6.0, 3.0, 0.5)


def _curv(artifact, settings=DEFAULT, seed=0):
    prep = prepare_scan(simulate_scan(artifact, settings, scanner=SC, seed=seed), scanner=SC)
    return prep, mean_curvature(prep)


@pytest.mark.parametrize("artifact, truth", [(Sphere(17.5), 1 / 17.5), (Sphere(27.5), 1 / 27.5),
                                             (Cylinder(20.0), 1 / 40.0), (Plane(), 0.0)])
def test_mean_curvature_of_known_shapes(artifact, truth) -> None:
    """Median within 4 % of the true mean curvature (1/R sphere, 1/(2r) cylinder, 0 plane ± 0.001 /mm), 80 % of the
    points within ±0.012 /mm at the default exposure."""
    _, c = _curv(artifact)
    ok = np.isfinite(c)
    assert ok.mean() > 0.95
    assert abs(np.median(c[ok]) - truth) <= max(0.04 * truth, 0.001)
    assert np.mean(np.abs(c[ok] - truth) < 0.012) > 0.8


def test_concave_and_sharp_shapes_and_unorganized_scans() -> None:
    """The bowl's pocket reads concave (negative), the step's edges far outside any training sphere; an unorganized
    scan gets NaN (not checked)."""
    pytest.importorskip("open3d")
    from xmetro_ros.parts.regions import REGIONS
    from xmetro_ros.parts.study import PRESENTATION, label_cad_regions
    from xmetro_ros.scan.generated_parts import make_part

    for name in ("bowl", "step"):
        prep, c = _curv(make_part(name).transformed(PRESENTATION))
        region, _ = label_cad_regions(make_part(name), np.asarray(prep.points))
        if name == "bowl":
            assert np.nanmedian(c[region == REGIONS.index("concave")]) < -0.03
        assert np.nanpercentile(np.abs(c[region == REGIONS.index("edge")]), 90) > 0.1
        assert abs(np.nanmedian(c[region == REGIONS.index("flat")])) < 0.003
    flat = grid_mean_curvature(np.asarray(prep.points), np.asarray(prep.normals), np.arange(len(prep)),
                               (len(prep),), 6.0, 3.0)
    assert np.isnan(flat).all()


def test_shape_domain_flags_what_training_never_saw(tmp_path) -> None:
    """The shipped card's shape domain (cells of the (κmin, κmax) plane its calibration points occupy: spheres, a
    cylinder and the calibration surfaces) keeps a sphere's points and the bowl's, and flags a Ø8 sphere (curved
    beyond 0.1 /mm both ways: no calibration surface is); a card without ``domain_shape`` checks nothing;
    ``_calibrate_default`` without the surfaces writes the mean-curvature range of its calibration clouds, which
    flags the bowl's pocket."""
    pytest.importorskip("open3d")
    from xmetro_ros.apps.train import _calibrate_default
    from xmetro_ros.parts.study import PRESENTATION
    from xmetro_ros.scan.generated_parts import make_part

    ms = ModelSet.load()
    assert ms.principal_domain is not None
    h = ScanHandler(ms, SC)
    st = ScanSettings(10.0, 4.0, 0.5)
    sphere = h.process(simulate_scan(Sphere(22.5), st, scanner=SC, seed=3))
    assert sphere.shape_out_of_domain is not None and sphere.shape_out_of_domain.mean() < 0.005
    bowl = h.process(simulate_scan(make_part("bowl").transformed(PRESENTATION), st, scanner=SC, seed=3))
    assert bowl.shape_out_of_domain.mean() < 0.01
    small = h.process(simulate_scan(Sphere(4.0), st, scanner=SC, seed=3))
    assert small.shape_out_of_domain.mean() > 0.9

    d = tmp_path / "m"
    shutil.copytree(default_model_dir(), d)
    card = json.loads((d / "card.json").read_text())
    del card["domain_shape"]
    (d / "card.json").write_text(json.dumps(card))
    assert ScanHandler(ModelSet.load(d), SC).process(bowl.scan).shape_out_of_domain is None
    _calibrate_default(d, "micro", 0, surfaces=False)
    block = json.loads((d / "card.json").read_text())["domain_shape"]
    assert block["lo"] < 0.0 < block["hi"] < 0.1 and block["n"] > 10_000 and "principal" not in block
    mc = ModelSet.load(d)
    lo, hi, radius = mc.shape_domain
    assert lo < 0.0 < 1 / 27.5 < 1 / 17.5 < hi and radius == 1.0
    old = ScanHandler(mc, SC).process(bowl.scan)
    c = mean_curvature(old.prepared)
    assert old.shape_out_of_domain[c < lo - 0.05 * (hi - lo)].all() and old.shape_out_of_domain.mean() > 0.3


def test_calibration_with_surfaces_gives_u_per_class_and_the_judge_uses_it(tmp_path) -> None:
    """``_calibrate_default`` with the calibration surfaces writes multipliers per surface class and the (κmin,
    κmax) shape domain; the judge then gives each point its class's U (the same bits as the model set's own call
    with the classes) and checks the shape in that plane: a saddle the calibration saw is in, the bowl's pocket
    (concave, like the calibration's groove and dimple) mostly in."""
    pytest.importorskip("open3d")
    from xmetro_ros.apps.train import _calibrate_default
    from xmetro_ros.parts.study import PRESENTATION
    from xmetro_ros.preprocess.curvature import principal_curvatures
    from xmetro_ros.scan.generated_parts import make_part

    d = tmp_path / "m"
    shutil.copytree(default_model_dir(), d)
    _calibrate_default(d, "micro", 0)
    card = json.loads((d / "card.json").read_text())
    by = card["uncertainty"]["conditional"]["by_surface"]
    assert by["classes"] == ["flat", "convex", "concave", "saddle", "sharp"]
    assert all(np.asarray(n).sum() > 500 for n in by["n"]), [np.asarray(n).sum() for n in by["n"]]
    assert len(card["domain_shape"]["principal"]["cells"]) > 50
    ms = ModelSet.load(d)
    assert ms.by_surface and ms.principal_domain is not None
    res = ScanHandler(ms, SC).process(simulate_scan(make_part("bowl").transformed(PRESENTATION),
                                                    ScanSettings(10.0, 4.0, 0.5), scanner=SC, seed=3))
    cls = ms.surface_classes(principal_curvatures(res.prepared))
    assert (cls == 2).mean() > 0.2  # the pocket
    # the per-class multipliers are calibrated on max(σ̂, measured noise·|N|), and the judge gives U the scan's noise
    assert ms.noise_in_u and by["noise"]["window_cells"] == 7 and res.noise is not None
    up = ms.predict_with_uncertainty(res.features, surface_class=cls, noise=res.noise)
    np.testing.assert_array_equal(res.row_uncertainty, up.U)
    plain = ms.predict_with_uncertainty(res.features)
    assert not np.array_equal(plain.U[cls == 0], up.U[cls == 0])
    assert res.shape_out_of_domain is not None and res.shape_out_of_domain[cls == 2].mean() < 0.2


def test_adding_the_surfaces_keeps_the_cards_own_calibration(tmp_path) -> None:
    """``_calibrate_default(..., keep_calibration=True)`` (``xmetro export-default --add-surfaces``, how the pose
    model's card got its per-class U): the card's all-class multipliers, conditions and multivariate domain — what
    the recommender uses — stay as they were, byte for byte; the per-class block (on the measured noise, with the
    clouds it came from) and the (κmin, κmax) shape domain are added, and the along-normal block with
    ``along_normal`` (a measured-tilt one), none without it; a card without conditional U is refused."""
    pytest.importorskip("open3d")
    from xmetro_ros.apps.train import _calibrate_default
    from xmetro_ros.judge.along_normal import AlongNormal

    d = tmp_path / "m"
    shutil.copytree(default_model_dir(), d)
    card = json.loads((d / "card.json").read_text())
    del card["uncertainty"]["conditional"]["by_surface"]
    del card["domain_shape"]["principal"]
    # an along-normal block fitted on other rows (0.9.1's kind), which the new calibration must not keep
    stale = AlongNormal(np.array([0.2236, 1.0]), np.full((3, 5), 2.0), np.full((9, 5, 3, 2), 0.3))
    card["uncertainty"]["along_normal"] = stale.to_block()
    (d / "card.json").write_text(json.dumps(card))
    _calibrate_default(d, "micro", 0, keep_calibration=True, by_source=True)
    new = json.loads((d / "card.json").read_text())
    u0, u1 = card["uncertainty"], new["uncertainty"]
    assert u1["multiplier"] == u0["multiplier"] and u1["sigma_max_mm"] == u0["sigma_max_mm"]
    assert u1["calibration_clouds"] == u0["calibration_clouds"]
    assert {k: v for k, v in u1["conditional"].items() if k != "by_surface"} == u0["conditional"]
    assert new["domain_mv"] == card["domain_mv"]
    by = u1["conditional"]["by_surface"]
    assert by["noise"]["window_cells"] == 7 and "sources" in by
    assert any("calibration surfaces" in c for c in by["calibration_clouds"])
    assert "principal" in new["domain_shape"] and ModelSet.load(d).by_surface
    assert "along_normal" not in u1  # re-calibrated without ``along_normal``: the stale block is gone
    (d / "card.json").write_text(json.dumps(card))
    _calibrate_default(d, "micro", 0, keep_calibration=True, along_normal=True)
    an = ModelSet.load(d).along_normal
    assert an is not None and an.needs_tilt and np.isfinite(an.allowance).any()

    del card["uncertainty"]["conditional"]
    (d / "card.json").write_text(json.dumps(card))
    with pytest.raises(ValueError, match="no conditional U"):
        _calibrate_default(d, "micro", 0, keep_calibration=True)
