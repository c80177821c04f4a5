"""Closed loop on lists of single laser-line profiles (``loop.inputs.from_profiles``): the real Standard Sphere Seg
training list (R = 19.05 mm, ../shared/data/measured/profiler_sphere_r19_labelled), read through ``load_inputs`` on
a small subset (8 sensor positions × 5 repeats = 40 profiles, written as a temporary list beside links to the data's
folders); bad lists; one short loop run. Never the data's test split."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from conftest import need_shared

from xmetro_ros.calibrate.profile_table import PROFILE_FEATURES, build_profile_table
from xmetro_ros.loop.candidates import build_candidates
from xmetro_ros.loop.data import LoopInputError
from xmetro_ros.loop.inputs import MEASURED_FEATURES, check_inputs, detect_kind, load_inputs
from xmetro_ros.loop.run import LoopConfig, run_loop
from xmetro_ros.loop.trace import TraceConfig
from xmetro_ros.scan.profiles import load_profile_list, parse_profile_name

R19 = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "measured" / "profiler_sphere_r19_labelled"
SPEC = "sphere:radius=19.05,center=fit"
N_POSITIONS, N_REPEATS = 8, 5


def _subset_list(tmp: Path, lines: list[str], name: str = "subset.txt") -> Path:
    """A list file in ``tmp`` naming ``lines`` (relative to the data's root), with links to the data's folders (a
    list names its profiles relative to its own folder)."""
    for folder in {Path(s.lstrip("/")).parts[0] for s in lines if s.strip()}:
        link = tmp / folder
        if not link.exists():
            link.symlink_to(R19 / folder, target_is_directory=True)
    path = tmp / name
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def subset(tmp_path_factory) -> tuple[Path, list[str]]:
    """Every 9th position of the training list that has exactly 5 repeats, 8 positions: 40 profiles."""
    need_shared(R19)
    by_pos: dict[str, list[str]] = defaultdict(list)
    for s in (R19 / "train_file.txt").read_text().split():
        by_pos[parse_profile_name(s.lstrip("/"))[0]].append(s)
    five = [names for names in by_pos.values() if len(names) == N_REPEATS]
    picked = five[::9][:N_POSITIONS]
    assert len(picked) == N_POSITIONS
    lines = [s for names in picked for s in names]
    return _subset_list(tmp_path_factory.mktemp("r19"), lines), lines


@pytest.fixture(scope="module")
def data(subset):
    return load_inputs([subset[0]], SPEC)


def test_profile_list_is_read_as_loop_data(subset, data):
    path, lines = subset
    assert detect_kind(path) == "profiles"
    n = data.n
    assert data.source == "profiles" and data.hold_by == "profile"
    assert data.points.shape == data.normals.shape == data.errors.shape == (n, 3)
    assert data.X.shape == (n, len(PROFILE_FEATURES)) and data.feature_names == PROFILE_FEATURES
    # In the laser plane: y = 0 for points, normals and errors.
    assert not data.points[:, 1].any() and not data.normals[:, 1].any() and not data.errors[:, 1].any()
    assert np.allclose(np.linalg.norm(data.normals, axis=1), 1.0, atol=1e-9)
    # Errors along the normals: e = (e·n) n.
    en = np.einsum("ij,ij->i", data.errors, data.normals)
    assert np.allclose(data.errors, en[:, None] * data.normals, atol=1e-12)
    assert 5e-3 < np.sqrt(np.mean(en**2)) < 0.1  # tens of µm, not a misfit (mm)
    # The table's kept points, one group per profile, in list order.
    tab = build_profile_table(load_profile_list(path), 19.05)
    assert n == int(tab.kept.sum())
    assert np.allclose(en, tab.deviation[tab.kept]) and np.allclose(data.X, tab.X[tab.kept])
    assert len(data.groups) == len(lines) == 40
    assert data.group_names == [s.lstrip("/") for s in lines]
    assert np.array_equal(data.group, tab.profile[tab.kept])
    # order: the rank along x inside each profile.
    for g in data.groups:
        rows = np.flatnonzero(data.group == g)
        assert np.array_equal(np.sort(data.order[rows]), np.arange(len(rows)))
        assert np.all(np.diff(data.points[rows[np.argsort(data.order[rows])], 0]) >= 0)
    # pose: one value per profile, shared by the repeats of a position, different between positions.
    pose_of = {g: np.unique(data.fields["pose"][data.group == g]) for g in data.groups}
    assert all(len(v) == 1 for v in pose_of.values())
    by_position: dict[str, set[float]] = defaultdict(set)
    for g, name in enumerate(data.group_names):
        by_position[parse_profile_name(name)[0]].add(float(pose_of[g][0]))
    assert len(by_position) == N_POSITIONS and all(len(v) == 1 for v in by_position.values())
    assert len({next(iter(v)) for v in by_position.values()}) == N_POSITIONS
    # The sensor axis toward the sensor: the kept arc faces it (within the 66° border angle).
    L = data.geometry["L"]
    assert np.allclose(np.abs(L[:, 2]), 1.0) and not L[:, :2].any()
    assert np.all(np.einsum("ij,ij->i", data.normals, L) > np.cos(np.radians(66.5)))
    assert np.array_equal(data.geometry["u"], data.points[:, 0])
    assert data.artifact["fit_center"] is True and "per profile" in data.artifact["fit"]
    assert data.artifact["n_positions"] == N_POSITIONS


def test_pose_is_an_identity_across_repeats(data):
    vals, info = build_candidates(data)
    assert info["field_pose"].kind == "identity"
    # Not combined with the profile (it would be profile_identity): the repeats share it.
    assert len(np.unique(vals["field_pose"])) == N_POSITIONS
    assert len(np.unique(vals["profile_identity"])) == 40


def test_profile_inputs_checks(subset, tmp_path):
    path, lines = subset
    assert check_inputs([path], SPEC, PROFILE_FEATURES)[0] == "profiles"
    with pytest.raises(LoopInputError, match="profile features"):
        check_inputs([path], SPEC, MEASURED_FEATURES)
    with pytest.raises(LoopInputError, match="sphere"):
        check_inputs([path], "cylinder:radius=19.05")
    with pytest.raises(LoopInputError, match="--artifact"):
        check_inputs([path], None)
    # A list naming a missing profile: the error names the list and the missing file.
    missing = _subset_list(tmp_path, [*lines[:3], "/label_out_1/no_such_9.csv"], "missing.txt")
    with pytest.raises(LoopInputError, match=r"missing\.txt.*no_such_9\.csv"):
        load_inputs([missing], SPEC)
    # Lines that are no profile files: the list, the line and the text.
    notprof = _subset_list(tmp_path, [*lines[:3], "label_out_1/readme.md"], "notprof.txt")
    with pytest.raises(LoopInputError, match=r"notprof\.txt:4: 'label_out_1/readme\.md' is not a profile file"):
        load_inputs([notprof], SPEC)
    empty = _subset_list(tmp_path, ["# nothing"], "empty.txt")
    with pytest.raises(LoopInputError, match=r"empty\.txt.*names no profile"):
        load_inputs([empty], SPEC)
    with pytest.raises(LoopInputError, match="does not exist"):
        load_inputs([tmp_path / "absent.txt"], SPEC)


def _candidates(rep: dict) -> dict[str, dict]:
    return {c["name"]: c for c in rep["iterations"][0]["candidates"]}


CFG = dict(iterations=60, max_iter=1, trace=TraceConfig(n_perm=49))


def test_loop_on_profiles_names_the_per_position_pattern(data):
    """The real subset (full candidate library, roles drawn by sensor position so that a role holds all repeats of
    its positions): the error that repeats at a position is a shape along the line, not a rigid offset (the arc
    fitted per profile takes each profile's offset). ``pose_line_pattern`` (position × 0.5 mm cells), held out
    across repeats, explains far more of the residual than the rigid per-pose offset or per-profile offsets, and it
    is the diagnostic finding; corrected from the other repeats of the eval positions, the eval MAE drops."""
    rep = run_loop(data, LoopConfig(**CFG, correction="offset")).report
    cand = _candidates(rep)
    pattern, pose, prof = cand["pose_line_pattern"], cand["field_pose"], cand["profile_identity"]
    assert pattern["kind"] == "identity" and pattern["significant"]
    assert pattern["score"] > 2 * max(pose["score"], prof["score"]) and pattern["score"] > 0.2
    (finding,) = rep["diagnostic"]["findings"]
    assert finding["variable"] == "pose_line_pattern"
    assert finding["structure"] == "per-position pattern along the laser line (0.5 mm cells)"
    assert rep["diagnostic"]["eval_with_offsets"]["normal"]["mae"] < 0.8 * rep["before"]["normal"]["mae"]
    # Roles by position: no position has repeats in two roles.
    role_of = {}
    for role, r in rep["roles"].items():
        for g in r["groups"]:
            pos = parse_profile_name(g)[0]
            assert role_of.setdefault(pos, role) == role
    assert rep["before"]["y"]["mae"] == 0.0
    assert 5.0 < 1e3 * rep["before"]["normal"]["mae"] < 40.0


def test_loop_finds_an_injected_per_position_offset(data):
    """The same subset with a rigid offset per sensor position added to the errors (N(0, 30 µm) per in-plane axis,
    shared by the repeats): `field_pose` explains it on held-out repeats (significant, score ≥ 0.05, above the
    per-profile identity) and is the diagnostic finding, a per-pose offset."""
    rng = np.random.default_rng(3)
    upos, inv = np.unique(data.fields["pose"], return_inverse=True)
    w = rng.normal(0.0, 0.030, (len(upos), 3))
    w[:, 1] = 0.0
    d = data.subset(np.arange(data.n))
    d.errors = d.errors + np.einsum("ij,ij->i", d.normals, w[inv])[:, None] * d.normals
    # The two identities of this question only (the cell-wise pattern would take the offsets too).
    rep = run_loop(d, LoopConfig(**CFG, correction="offset", candidates=["field_pose", "profile_identity"])).report
    cand = _candidates(rep)
    assert cand["field_pose"]["significant"] and cand["field_pose"]["score"] >= 0.05
    assert cand["field_pose"]["score"] > cand["profile_identity"]["score"]
    (finding,) = rep["diagnostic"]["findings"]
    assert finding["variable"] == "field_pose" and finding["structure"] == "per-pose rigid offset"
    assert rep["diagnostic"]["eval_with_offsets"]["normal"]["mae"] < rep["before"]["normal"]["mae"]


def test_cli_on_a_profile_list(subset, tmp_path, capsys):
    """`xmetro loop LIST.txt --artifact sphere:...`: exit 0 and a report of the profiles; a bad list exits 2 with the
    list and the line named."""
    import argparse
    import json

    from xmetro_ros.apps import loop as cli

    def run(argv: list[str]) -> int:
        parser = argparse.ArgumentParser()
        cli.register(parser.add_subparsers())
        args = parser.parse_args(["loop", *argv])
        return args.func(args)

    path, lines = subset
    out = tmp_path / "out"
    assert run([str(path), "--artifact", SPEC, "--out", str(out), "--n-perm", "19", "--iterations", "40",
                "--max-iter", "1"]) == 0, capsys.readouterr().err
    rep = json.loads((out / "report.json").read_text())
    assert rep["source"] == "profiles" and rep["hold_by"] == "profile" and rep["n_groups"] == 40
    assert rep["artifact"]["fit_center"] is True and rep["model"]["features"] == PROFILE_FEATURES
    bad = _subset_list(tmp_path, [*lines[:2], "label_out_1/6_1.xyz"], "bad.txt")
    assert run([str(bad), "--artifact", SPEC, "--out", str(out)]) == 2
    assert "bad.txt:3" in capsys.readouterr().err
