"""Train where you search: the study campaign at the head orientations the rescan recommender explores."""

from __future__ import annotations

import numpy as np
import pytest

from xmetro_ros.scan.artifacts import Cylinder, Sphere
from xmetro_ros.scan.geometry import orientation_grid
from xmetro_ros.scan.scanner import ScannerModel
from xmetro_ros.sim.campaign import campaign_manifest, campaign_pose, pose_grid, study_campaign

SC = ScannerModel.load()


def test_pose_grid_is_the_search_grid():
    g = pose_grid()
    assert len(g) == 27 and sum(np.allclose(r, np.eye(3)) for r in g) == 1
    assert all(np.allclose(a, b) for a, b in zip(g, orientation_grid(0.2618, 3, 1.5708, 3), strict=True))
    assert len(pose_grid(0.1, 5, 1.0, 3)) == 75


def test_campaign_without_poses_unchanged():
    a, b = study_campaign(SC, seed=3), study_campaign(SC, seed=3, poses=None)
    assert [(i.seed, i.config_index, i.pose) for i in a] == [(i.seed, i.config_index, None) for i in b]
    assert "pose" not in a[0].describe()


def test_campaign_with_poses_layout():
    g = pose_grid()
    items = study_campaign(SC, seed=0, poses=g)  # cycle: the campaign keeps its 108 scans
    assert len(items) == 108 and len({i.seed for i in items}) == 108
    for ai in range(4):  # each artifact: every pose once, every configuration once
        part = items[27 * ai: 27 * (ai + 1)]
        assert sorted(i.pose_index for i in part) == list(range(27))
        assert sorted(i.config_index for i in part) == list(range(27))
    allp = study_campaign(SC, seed=0, poses=g[:3], pose_mode="all", sphere_diameters=(35.0,), cylinder=False)
    assert len(allp) == 81 and [i.pose_index for i in allp[::27]] == [0, 1, 2]
    man = campaign_manifest(items, seed=0)
    q = np.array(man["items"][5]["pose"]["quaternion_xyzw"])
    assert np.linalg.norm(q) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="pose_mode"):
        study_campaign(SC, poses=g, pose_mode="some")


def test_campaign_pose_cycles():
    """``pose_cycles`` n: each configuration from n poses, the first cycle the campaign of n = 1 item for item."""
    g = pose_grid()
    one, two = study_campaign(SC, seed=0, poses=g), study_campaign(SC, seed=0, poses=g, pose_cycles=2)
    assert len(two) == 216 and len({i.seed for i in two}) == 216
    for ai in range(4):
        part = two[54 * ai: 54 * (ai + 1)]
        assert [(i.pose_index, i.config_index) for i in part[:27]] == \
            [(i.pose_index, i.config_index) for i in one[27 * ai: 27 * (ai + 1)]]
        per_config = {c: {i.pose_index for i in part if i.config_index == c} for c in range(27)}
        assert all(len(p) == 2 for p in per_config.values())  # two different poses for every configuration
        assert sorted(i.pose_index for i in part) == sorted(list(range(27)) * 2)
    assert [(i.seed, i.pose_index) for i in one[:27]] == [(i.seed, i.pose_index) for i in two[:27]]
    for bad in (0, 28, 1.5):
        with pytest.raises(ValueError, match="pose_cycles"):
            study_campaign(SC, poses=g, pose_cycles=bad)


@pytest.mark.parametrize("artifact", [Sphere(17.5), Sphere(27.5), Cylinder(20.0)], ids=["s35", "s55", "cyl"])
def test_rotated_campaign_scans_cover_the_artifact(artifact):
    """Every pose of the grid scans the artifact's top as fully as looking down: no empty scan, the pivot (top of
    the artifact) seen, the covered extent within 15 % of the looking-down one, the pivot at the stand-off."""
    st = SC.study_configurations()[0]  # coarsest grid: quick
    items = study_campaign(SC, seed=1, poses=pose_grid(), pose_mode="all", artifacts=[artifact], configurations=[st])
    ident = next(i for i in items if np.allclose(i.pose.rotation, np.eye(3)))
    p0 = campaign_pose(artifact, np.eye(3), SC)
    assert np.allclose(ident.pose.position, p0.position) and np.allclose(ident.pose.rotation, p0.rotation)
    pivot = artifact.project(np.array([[0.0, 0.0, 100.0]]))[0]  # the top of the artifact: the rotations' pivot

    def nominal(it):
        p = it.simulate().points.reshape(-1, 3)
        return artifact.project(p[np.isfinite(p).all(axis=1)])

    ref = nominal(ident)
    ref_ext = np.ptp(ref[:, :2], axis=0)
    for it in items:
        # rotations about the pivot: it keeps its head-frame coordinates (stand-off, place in the scan)
        np.testing.assert_allclose(it.pose.to_head(pivot), ident.pose.to_head(pivot), atol=1e-9)
        nom = nominal(it)
        assert len(nom) > 0.85 * len(ref), it.pose_index
        assert np.min(np.linalg.norm(nom - pivot, axis=1)) < 0.5
        assert np.all(np.ptp(nom[:, :2], axis=0) > 0.85 * ref_ext), it.pose_index


def test_default_profile_campaign_balances_poses_against_settings():
    """The default model's profile (issue 15): the full campaign from the search's poses, cycled in an order that
    never ties a pose axis to a setting (the grid's own order never puts lateral 15/mm at a -90 deg turn)."""
    from xmetro_ros.learn.families import PROFILES, balanced_pose_order

    full, dflt = PROFILES["full"], PROFILES["default"]
    assert "poses" not in full.campaign and dflt.campaign["pose_mode"] == "cycle"
    order = [np.asarray(r) for r in balanced_pose_order()]
    g = pose_grid()
    perm = [min(range(27), key=lambda j, r=r: float(np.abs(g[j] - r).max())) for r in order]
    assert sorted(perm) == list(range(27))  # the same 27 poses, reordered
    items = study_campaign(SC, seed=0, poses=order)
    assert len(items) == 108

    def digits(k: int) -> tuple[int, int, int]:  # (lateral, direction, exposure) / (turn, tilt X, tilt Y) levels
        return k // 9, (k // 3) % 3, k % 3

    for s in range(3):
        for p in range(3):
            counts = [[0] * 3 for _ in range(3)]
            for it in items:
                assert it.pose_index is not None
                counts[digits(it.config_index)[s]][digits(perm[it.pose_index])[p]] += 1
            assert min(min(row) for row in counts) >= 10, (s, p, counts)
