"""The product's own segmentation of a sphere's arc in one profile (preprocess.profile_arc): synthetic profiles
with a known circle among a table, a post and stray returns, and the real labelled profiles scored against their
labels (IoU), never using them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import need_shared

from xmetro_ros.calibrate.profile_metrics import segmentation_iou
from xmetro_ros.calibrate.profile_table import build_profile_table
from xmetro_ros.preprocess.profile_arc import ARC_MAX_ANGLE_DEG, ArcFitError, segment_sphere_arc, sphere_offset
from xmetro_ros.scan.profiles import load_profile_list

R19 = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "measured" / "profiler_sphere_r19_labelled"


def _profile(r=15.0, c=(2.0, 230.0), toward=1, noise=0.01, seed=0, clutter=True):
    """A sensor-frame profile: the near half of a circle (sensor at larger z when toward=+1), a table and a post."""
    rng = np.random.default_rng(seed)
    a = np.radians(np.linspace(-85, 85, 400))
    arc = np.column_stack([c[0] + r * np.sin(a), c[1] + toward * r * np.cos(a)])
    arc += rng.normal(0, noise, arc.shape) * np.column_stack([np.sin(a), np.cos(a)])
    parts = [arc]
    if clutter:
        tx = np.linspace(-40, 40, 500)
        table = np.column_stack([tx, np.full_like(tx, c[1] - toward * 115.0) + rng.normal(0, 0.02, tx.size)])
        tx = tx[np.abs(tx - c[0]) > r + 1]  # the table is hidden under the sphere
        table = table[np.abs(table[:, 0] - c[0]) > r + 1]
        pz = np.linspace(c[1] - toward * 110, c[1] - toward * 30, 80)
        post = np.column_stack([np.full_like(pz, c[0] + 4.0), pz])
        stray = rng.uniform([-40, c[1] - 120], [40, c[1] + 20], size=(30, 2))
        parts += [table, post, stray]
    xz = np.vstack(parts)
    truth = np.zeros(len(xz), bool)
    truth[: len(arc)] = True
    return xz, truth, np.degrees(a)


@pytest.mark.parametrize("toward", [1, -1])
def test_finds_the_arc_among_clutter(toward):
    xz, truth, ang = _profile(toward=toward)
    s = segment_sphere_arc(xz, 19.05)
    assert s.toward == toward
    assert np.allclose(s.center, (2.0, 230.0), atol=0.01) and abs(s.radius - 15.0) < 0.01
    assert s.rms < 0.02
    # Nothing of the table, post or stray returns is on the arc; the arc is, up to the refit band.
    assert not np.any(s.on_arc[~truth]) or np.mean(s.on_arc[~truth]) < 0.01
    assert np.mean(s.on_arc[truth]) > 0.97
    # Kept = on the arc within the border angle; the signed angle is the generating one.
    np.testing.assert_allclose(s.angle_deg[: len(ang)], ang, atol=0.2)
    assert not np.any(s.kept[: len(ang)][np.abs(ang) > ARC_MAX_ANGLE_DEG + 0.5])
    assert np.all(s.kept[: len(ang)][(np.abs(ang) < ARC_MAX_ANGLE_DEG - 0.5)] | ~s.on_arc[: len(ang)][
        np.abs(ang) < ARC_MAX_ANGLE_DEG - 0.5])
    n = s.normals
    np.testing.assert_allclose(np.hypot(n[:, 0], n[:, 1]), 1.0, atol=1e-9)


def test_same_answer_for_the_same_seed_and_any_point_order():
    xz, _, _ = _profile(seed=3)
    a = segment_sphere_arc(xz, 19.05, seed=1)
    b = segment_sphere_arc(xz, 19.05, seed=1)
    assert np.array_equal(a.kept, b.kept)
    perm = np.random.default_rng(0).permutation(len(xz))
    c = segment_sphere_arc(xz[perm], 19.05, seed=1)
    assert np.allclose(c.center, a.center, atol=0.005) and np.array_equal(c.kept, a.kept[perm])


def test_no_arc_of_the_sphere_size():
    x = np.linspace(-20, 20, 300)
    with pytest.raises(ArcFitError):
        segment_sphere_arc(np.column_stack([x, 0.001 * x + 100.0]), 19.05)  # a flat table only
    xz, _, _ = _profile(r=30.0, clutter=False)  # a circle larger than the sphere cannot be its section
    with pytest.raises(ArcFitError):
        segment_sphere_arc(xz, 19.05)
    with pytest.raises(ArcFitError):
        segment_sphere_arc(np.zeros((5, 2)), 19.05)
    with pytest.raises(ValueError, match="non-finite"):
        segment_sphere_arc(np.array([[0.0, np.inf]] * 20), 19.05)


def test_sphere_offset():
    assert sphere_offset(19.05, 19.05, -1) == 0.0
    assert sphere_offset(5.0, 3.0, -1) == pytest.approx(-4.0)
    assert sphere_offset(5.0, 3.0, 1) == pytest.approx(4.0)


def test_real_validation_profiles_against_their_labels():
    """Issue 25: IoU of the kept points with the label-1 points, median ≥ 0.90 over the validation list, and no
    profile whose arc is the mount or the table (IoU < 0.5)."""
    need_shared(R19 / "val_file.txt")
    recs = load_profile_list(R19 / "val_file.txt")
    table = build_profile_table(recs, 19.05)
    assert not table.failures
    iou = segmentation_iou(table, np.arange(len(table.names)))
    assert np.median(iou) >= 0.90, np.median(iou)
    assert iou.min() >= 0.5, [table.names[i] for i in np.flatnonzero(iou < 0.5)]
    # Every arc is a plane section of the certified sphere: radius at most R (+ noise).
    assert table.arc_radius.max() < 19.05 * 1.01
