"""Any mesh scanned from the command line, one pose convention (issue 28): ``xmetro simulate --artifact
mesh:path=PART.stl,pose=x;y;z;qx;qy;qz;qw,form_error=UM`` and ``xmetro parts scan PART.stl OUT.mcap --pose ...``
scan a user's mesh placed by a pose in metres + quaternion (the node's ``cad_pose``), with the generated parts'
form error whose truth the bag keeps; bad specifications and the old 12-number millimetre pose are refused with a
clear message (the latter with the 7 numbers to use)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from xmetro_ros.apps.cli import main
from xmetro_ros.scan.artifact_specs import artifact_from_dict, parse_artifact
from xmetro_ros.scan.artifacts import ArtifactSpecError
from xmetro_ros.scan.generated_parts import apply_form_error, form_field, make_part, refine_edges
from xmetro_ros.scan.mesh import MeshArtifact, write_stl
from xmetro_ros.scan.part_pose import PoseError, format_pose7, matrix_mm_to_pose7, parse_pose7, pose7_to_matrix_mm
from xmetro_ros.scan.scanner import ScannerModel
from xmetro_ros.sim import simulate_scan

OUTLIERS_OFF = {"outliers": {"enabled": False}}

# The pose of the tests, as a user writes it: 0.3 mm, 0.2 mm, 8 mm (in metres), turned 5° about Z and tilted 2°
# about X (quaternion x, y, z, w).
QUAT = Rotation.from_euler("zx", [5.0, 2.0], degrees=True).as_quat()
POSE7 = [0.0003, 0.0002, 0.008, *QUAT]


def _pose_mm() -> np.ndarray:
    """The same pose as a (4, 4) mm transform, built here with scipy (independent of xmetro's reader)."""
    t = np.eye(4)
    t[:3, :3] = Rotation.from_quat(QUAT).as_matrix()
    t[:3, 3] = np.array(POSE7[:3]) * 1000.0
    return t


def _box(half=(15.0, 12.0, 5.0)) -> tuple[np.ndarray, np.ndarray]:
    """A closed box centred at the origin (mm), outward winding: 8 vertices, 12 triangles."""
    hx, hy, hz = half
    v = np.array([[x, y, z] for x in (-hx, hx) for y in (-hy, hy) for z in (-hz, hz)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert (np.einsum("ij,ij->i", n, v[f].mean(axis=1)) > 0).all()  # outward
    return v, f


@pytest.fixture(scope="module")
def box_stl(tmp_path_factory):
    v, f = _box()
    return write_stl(tmp_path_factory.mktemp("mesh") / "box.stl", v, f), v, f


def _scans(bag):
    from xmetro_ros.ros.scan_io import read_scans

    return read_scans(bag)


def _residuals(points: np.ndarray, expected: np.ndarray, truth: MeshArtifact, form: dict | None = None
               ) -> np.ndarray:
    """(N, 3) µm: the error of ``points`` against ``truth`` (nominal − measured; the test's own posed mesh) minus
    the simulator's recorded systematic error ``expected``: the noise, when the points lie on ``truth``. With
    ``form`` (the kept truth of the form error), ``truth`` is the CAD and the manufactured surface lies the form
    error's part along the CAD normal beyond it."""
    p = np.asarray(points, dtype=np.float64)
    actual = truth.errors(p)
    if form is not None:
        t = np.asarray(truth.transform)
        p_part = (p - t[:3, 3]) @ t[:3, :3]
        f = form_field(p_part, form["form_um"], center_mm=form["form_center_mm"], sigma_mm=form["form_sigma_mm"])
        n = truth.normals(p)
        z = t[:3, :3] @ np.array([0.0, 0.0, 1.0])  # the part's +Z in the scan frame: the form error's direction
        actual = actual + (f * (n @ z))[:, None] * n
    return (actual - np.asarray(expected, dtype=np.float64)) * 1e3


def _score(scan, twin: MeshArtifact, truth: MeshArtifact, form: dict | None = None,
           effects: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(residuals (N, 3) µm of ``_residuals``, the simulator's noise s.d. at those points (N,) µm, norm over the
    axes). The noise comes from the same scan simulated here (same settings and seed) of ``twin``; its injected
    outliers are left out."""
    s2 = simulate_scan(twin, scan.settings, scanner=ScannerModel.load(), seed=scan.meta["seed"], effects=effects)
    ok = np.isfinite(scan.points).all(axis=-1)
    assert (ok == np.isfinite(s2.points).all(axis=-1)).mean() > 0.999  # the same rays hit
    keep = ok & np.isfinite(s2.points).all(axis=-1) & ~np.asarray(s2.injected_outlier, bool)
    r = _residuals(scan.points[keep], scan.expected_error[keep], truth, form)
    return r, np.linalg.norm(s2.noise_std[keep], axis=1) * 1e3


def _noise_ratio(r: np.ndarray, sigma: np.ndarray) -> float:
    """RMS of |r| over the RMS of the simulator's noise s.d.: 1 when r is that noise. Points whose s.d. is over
    5× the median are left out (the noise's Jacobian across a crease: a few, up to millimetres)."""
    m = sigma < 5.0 * np.median(sigma)
    return float(np.sqrt(np.mean(np.sum(r[m] ** 2, axis=1))) / np.sqrt(np.mean(sigma[m] ** 2)))


def _assert_noise(r: np.ndarray, sigma: np.ndarray, what) -> None:
    """The residuals are the simulator's noise: their RMS is the noise's (measured 0.997-1.026), all points but
    1 in 1000 within 5 σ (a few at the box's edges, where a noisy point projects onto the other face), no bias
    beyond 0.1 σ (measured ≤ 0.04 σ)."""
    assert 0.9 < _noise_ratio(r, sigma) < 1.1, what
    assert np.mean(np.linalg.norm(r, axis=1) <= 5.0 * sigma) > 0.999, what
    assert (np.abs(r.mean(axis=0)) < 0.1 * sigma.mean()).all(), what


# --- the pose: one reader, the old form refused -------------------------------------------------------------------

def test_pose7_reader_and_the_old_form_refused() -> None:
    t = _pose_mm()
    for text in (" ".join(map(str, POSE7)), ",".join(map(str, POSE7)), ";".join(map(str, POSE7)),
                 "[" + ", ".join(map(str, POSE7)) + "]"):
        np.testing.assert_allclose(parse_pose7(text), t, atol=1e-12)
    np.testing.assert_allclose(pose7_to_matrix_mm(matrix_mm_to_pose7(t)), t, atol=1e-12)
    np.testing.assert_allclose(parse_pose7(format_pose7(t)), t, atol=1e-9)
    assert np.array_equal(parse_pose7(None), np.eye(4)) and np.array_equal(parse_pose7(""), np.eye(4))
    # 12 numbers: the ≤ 0.5 millimetre matrix, refused with what changed and the same pose in the new form
    old = " ".join(f"{x:.12g}" for x in t[:3].ravel())
    with pytest.raises(PoseError, match=r"12 numbers .* no longer read") as e:
        parse_pose7(old, what="--cad-pose")
    msg = str(e.value)
    assert "--cad-pose" in msg and "metres and a quaternion" in msg
    suggested = msg.split("The same pose: \"")[1].split("\"")[0]
    np.testing.assert_allclose(parse_pose7(suggested), t, atol=1e-9)  # paste it: the same pose
    with pytest.raises(PoseError, match="not a rotation"):
        parse_pose7("2 0 0 0 0 1 0 0 0 0 1 0")
    for bad, match in (("1 2 3", "needs 7 numbers.*got 3"), ("0 0 0 0 0 0 0", "quaternion .* is zero"),
                       ("0 0 nan 0 0 0 1", "finite"), ("0 0 x 0 0 0 1", "not numbers")):
        with pytest.raises(PoseError, match=match):
            parse_pose7(bad)


def test_every_command_refuses_the_old_pose(box_stl, tmp_path, capsys) -> None:
    """`xmetro predict --cad-pose` (and `--param cad_pose=`), `xmetro parts scan --pose`, `xmetro simulate
    --artifact mesh:...,pose=`: the 12-number form is an error (nothing judged or written) whose message gives the
    7 numbers to use."""
    stl = box_stl[0]
    old = "1 0 0 0.37 0 1 0 0.21 0 0 1 12"
    rc = main(["predict", str(tmp_path / "in.mcap"), "--out", str(tmp_path / "out.mcap"), "--cad", str(stl),
               "--cad-pose", old])
    err = capsys.readouterr().err
    assert rc == 1 and "12 numbers" in err and '"0.00037 0.00021 0.012 0 0 0 1"' in err, err
    assert not (tmp_path / "out.mcap").exists()
    rc = main(["predict", str(tmp_path / "in.mcap"), "--out", str(tmp_path / "out.mcap"), "--param",
               f"cad_pose={old.replace(' ', ',')}"])
    err = capsys.readouterr().err
    assert rc == 1 and '"0.00037,0.00021,0.012,0,0,0,1"' in err, err
    rc = main(["parts", "scan", str(stl), str(tmp_path / "p.mcap"), "--pose", old])
    err = capsys.readouterr().err
    assert rc == 2 and '"0.00037,0.00021,0.012,0,0,0,1"' in err, err
    rc = main(["simulate", "--out", str(tmp_path / "sim"), "--quick", "--artifact",
               f"mesh:path={stl},pose={old.replace(' ', ';')}"])
    err = capsys.readouterr().err
    assert rc == 2 and '"0.00037;0.00021;0.012;0;0;0;1"' in err, err
    assert not (tmp_path / "p.mcap").exists() and not (tmp_path / "sim").exists()


# --- the mesh specification -----------------------------------------------------------------------------------------

def test_mesh_spec_and_its_errors(box_stl, tmp_path) -> None:
    stl, v, _ = box_stl
    spec = f"mesh:path={stl},pose={';'.join(map(str, POSE7))}"
    mesh, fit = parse_artifact(spec)
    assert isinstance(mesh, MeshArtifact) and not fit
    np.testing.assert_allclose(mesh.transform, _pose_mm(), atol=1e-12)
    t = _pose_mm()

    def rows(a):
        return a[np.lexsort(a.T[::-1])]

    np.testing.assert_allclose(rows(mesh.vertices), rows(v @ t[:3, :3].T + t[:3, 3]), atol=1e-9)
    # the record rebuilds the same posed mesh (a bag's scan record)
    back = artifact_from_dict(mesh.to_dict())
    np.testing.assert_allclose(back.vertices, mesh.vertices, atol=1e-12)
    # with a form error: the manufactured mesh, its truth in the record, rebuilt identically
    man, _ = parse_artifact(spec + ",form_error=35:8")
    src = man.to_dict()["source"]
    assert src["form_um"] == 35.0 and src["form_sigma_mm"] == 8.0 and src["form_center_mm"] == [0.0, 0.0]
    np.testing.assert_allclose(artifact_from_dict(man.to_dict()).vertices, man.vertices, atol=1e-12)
    (tmp_path / "junk.stl").write_bytes(b"solid junk\n" * 10)
    (tmp_path / "notes.txt").write_text("x")
    for bad, match in [
        ("mesh:", "needs path="),
        (f"mesh:path={tmp_path / 'none.stl'}", "not found"),
        (f"mesh:path={tmp_path / 'notes.txt'}", "unknown mesh format"),
        (f"mesh:path={tmp_path / 'junk.stl'}", "no triangles|cannot read"),
        (f"mesh:path={stl},pose=0;0;0.01", "needs 7 numbers.*got 3"),
        (f"mesh:path={stl},pose=0;0;0;0;0;0;0", "quaternion .* is zero"),
        (f"mesh:path={stl},pose=0;0;inf;0;0;0;1", "finite"),
        (f"mesh:path={stl},pose=0,0,0,0,0,0,1", "separated by ';'"),
        (f"mesh:path={stl},form_error=big", "AMPLITUDE_UM"),
        (f"mesh:path={stl},form_error=35:0", "positive"),
        (f"mesh:path={stl},radius=3", "unknown option"),
    ]:
        with pytest.raises(ArtifactSpecError, match=match):
            parse_artifact(bad)


def test_refine_edges_keeps_the_surface_and_the_form_error_follows_the_field() -> None:
    v, f = _box()
    rv, rf = refine_edges(v, f, 1.5)
    e = np.sort(np.concatenate([rf[:, [0, 1]], rf[:, [1, 2]], rf[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    assert (counts == 2).all()  # closed, no crack: every edge shared by two triangles
    assert np.linalg.norm(rv[e[:, 0]] - rv[e[:, 1]], axis=1).max() <= 1.5

    def volume(vv, ff):
        return np.einsum("ij,ij->i", vv[ff[:, 0]], np.cross(vv[ff[:, 1]], vv[ff[:, 2]])).sum() / 6

    assert volume(rv, rf) == pytest.approx(volume(v, f), rel=1e-12)  # same solid, same winding
    # the generated parts' form error on any mesh: on a generated part it is make_part's
    cad = make_part("step", step_mm=1.0)
    cad = MeshArtifact(cad.vertices, cad.triangles, name="step")
    man = apply_form_error(cad, 40.0)
    ref = make_part("step", form_um=40.0, step_mm=1.0)
    pts, _ = ref.sample(4000, seed=3)
    pts = pts[pts[:, 2] > -11.9]  # not the bottom, a fan of long triangles in make_part (split here)
    assert np.abs(man.project(pts) - pts).max() < 0.4e-3  # within 1 % of the amplitude


# --- xmetro simulate / xmetro parts scan on a mesh --------------------------------------------------------------

def test_simulate_scans_the_posed_mesh(box_stl, tmp_path) -> None:
    """`xmetro simulate --artifact mesh:path=box.stl,pose=...`: every point lies on the box where the pose (m +
    quaternion) puts it: its error against the test's own posed box is the simulator's systematic error plus
    noise; against the unposed box it is millimetres."""
    pytest.importorskip("open3d")
    stl, v, f = box_stl
    out = tmp_path / "sim"
    rc = main(["simulate", "--out", str(out), "--quick", "--effects-off", "outliers", "--artifact",
               f"mesh:path={stl},pose={';'.join(map(str, POSE7))}"])
    assert rc == 0
    scans = _scans(out / "campaign.mcap")
    assert len(scans) == 3
    truth = MeshArtifact(v, f).transformed(_pose_mm())
    for scan in scans:
        assert scan.n_valid > 2000 and scan.artifact.kind == "mesh"
        np.testing.assert_allclose(scan.artifact.transform, _pose_mm(), atol=1e-12)
        r, sigma = _score(scan, truth, truth, effects=OUTLIERS_OFF)
        _assert_noise(r, sigma, scan.settings)
        # the pose matters: the same points against the box where it would be without the pose
        ok = np.isfinite(scan.points).all(axis=-1)
        off = _residuals(scan.points[ok], scan.expected_error[ok], MeshArtifact(v, f))
        assert np.median(np.linalg.norm(off, axis=1)) > 1000.0


def test_simulate_with_a_form_error_scores_against_the_kept_truth(box_stl, tmp_path) -> None:
    """`form_error=100`: the points lie on the box + the form error; the bag keeps its truth (amplitude, σ,
    centre), which scores the scan: against the CAD plus the kept form error, noise; against the CAD alone, the
    form error."""
    pytest.importorskip("open3d")
    stl, v, f = box_stl
    out = tmp_path / "sim"
    rc = main(["simulate", "--out", str(out), "--quick", "--effects-off", "outliers", "--artifact",
               f"mesh:path={stl},pose={';'.join(map(str, POSE7))},form_error=100"])
    assert rc == 0
    cad = MeshArtifact(v, f).transformed(_pose_mm())
    twin = apply_form_error(MeshArtifact.from_file(stl), 100.0).transformed(_pose_mm())  # for the noise s.d. only
    for scan in _scans(out / "campaign.mcap"):
        form = scan.artifact.to_dict()["source"]
        assert form["form_um"] == 100.0 and form["form_sigma_mm"] == 6.0 and scan.meta["artifact"]["source"] == form
        r, sigma = _score(scan, twin, cad, form, effects=OUTLIERS_OFF)
        _assert_noise(r, sigma, scan.settings)
        raw, sigma = _score(scan, twin, cad, None, effects=OUTLIERS_OFF)  # the form error left in
        assert _noise_ratio(raw, sigma) > 2.0 and np.percentile(np.abs(raw[:, 2]), 99) > 70.0  # measured 2.7-5.2


def test_parts_scan_takes_a_mesh(box_stl, tmp_path, capsys) -> None:
    """`xmetro parts scan box.stl OUT.mcap --pose ...`: one scan of the manufactured box (40 µm form error) where
    the pose puts it; the printed --cad-pose is the same pose in the same 7 numbers."""
    pytest.importorskip("open3d")
    stl, v, f = box_stl
    out = tmp_path / "box.mcap"
    rc = main(["parts", "scan", str(stl), str(out), "--pose", ",".join(map(str, POSE7)), "--settings", "6,3,0.5"])
    assert rc == 0
    printed = capsys.readouterr().out
    cad_pose = printed.split('--cad-pose "')[1].split('"')[0]
    np.testing.assert_allclose(parse_pose7(cad_pose), _pose_mm(), atol=1e-9)
    assert f"CAD {stl}" in printed
    (scan,) = _scans(out)
    form = scan.artifact.to_dict()["source"]
    assert form["form_um"] == 40.0
    assert scan.n_valid > 2000
    twin = apply_form_error(MeshArtifact.from_file(stl), 40.0).transformed(_pose_mm())
    r, sigma = _score(scan, twin, MeshArtifact(v, f).transformed(_pose_mm()), form)  # every effect, outliers left out
    _assert_noise(r, sigma, scan.settings)
    assert main(["parts", "scan", str(tmp_path / "missing.stl"), str(tmp_path / "m.mcap")]) == 2
    assert "not found" in capsys.readouterr().err
    assert main(["parts", "scan", "cube", str(tmp_path / "m.mcap")]) == 2
    assert "or a mesh file" in capsys.readouterr().err
    assert not (tmp_path / "m.mcap").exists()
