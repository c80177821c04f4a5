"""Profile files (scan.profiles): CSV / NumPy forms, names → positions and sides, typed errors (fuzzed), and the
real labelled data set's lists read in place."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import need_shared
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from xmetro_ros.scan.profiles import ProfileDataError, load_profile_list, parse_profile_name, read_profile

R19 = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "measured" / "profiler_sphere_r19_labelled"


def test_names_give_position_repeat_and_side():
    assert parse_profile_name("label_out_1/m_6_2.csv") == ("label_out_1/m_6", 2, -1)
    assert parse_profile_name("label_out_1/6_2.csv") == ("label_out_1/6", 2, 1)
    assert parse_profile_name("label_out_7/m6_3.csv") == ("label_out_7/m_6", 3, -1)
    assert parse_profile_name("a/run.csv") == ("a/run", 0, 1)
    assert parse_profile_name("a/main_2.csv") == ("a/main", 2, 1)
    # Repeats in different folders are different positions.
    assert parse_profile_name("a/5_1.csv")[0] != parse_profile_name("b/5_1.csv")[0]


def test_csv_with_header_labels_and_no_returns(tmp_path):
    f = tmp_path / "m_3_1.csv"
    f.write_text("x,z,label\n1.0,200.5,1\n1.5,inf,0\n2.0,nan,0\n2.5,201.0,0\n")
    r = read_profile(f, root=tmp_path)
    assert r.name == "m_3_1.csv" and r.position == "./m_3" and r.repeat == 1 and r.side == -1
    np.testing.assert_array_equal(r.xz, [[1.0, 200.5], [2.5, 201.0]])  # +inf / NaN ranges dropped
    np.testing.assert_array_equal(r.label, [1, 0])


def test_numpy_forms(tmp_path):
    xz = np.array([[0.0, 1.0], [1.0, 2.0], [2.0, np.inf]])
    np.save(tmp_path / "p_1.npy", xz)
    assert len(read_profile(tmp_path / "p_1.npy")) == 2
    np.savez(tmp_path / "p_2.npz", xz=xz[:2], label=np.array([1, 0]))
    r = read_profile(tmp_path / "p_2.npz")
    assert r.label is not None and list(r.label) == [1, 0]
    np.savez(tmp_path / "bad.npz", points=xz)
    with pytest.raises(ProfileDataError, match="no array 'xz'"):
        read_profile(tmp_path / "bad.npz")
    np.save(tmp_path / "bad.npy", np.zeros((3, 5)))
    with pytest.raises(ProfileDataError, match=r"\(N, 2\) or \(N, 3\)"):
        read_profile(tmp_path / "bad.npy")


@pytest.mark.parametrize("text, match", [
    ("", "no points"),
    ("1,2\n3\n", "expected x, z"),
    ("1,2\n3,4,1\n", "expected x, z"),
    ("1,2\n3,abc\n", "not a number"),
    ("1,2,7\n", "labels must be 0 or 1"),
    ("nan,1\n", "no finite point"),
])
def test_bad_csv_names_the_file(tmp_path, text, match):
    f = tmp_path / "p_1.csv"
    f.write_text(text)
    with pytest.raises(ProfileDataError, match=match) as e:
        read_profile(f)
    assert "p_1.csv" in str(e.value)


def test_list_file_errors(tmp_path):
    (tmp_path / "a_1.csv").write_text("1,2\n2,3\n")
    lst = tmp_path / "list.txt"
    lst.write_text("/a_1.csv\n\n# a comment\n")
    assert [r.name for r in load_profile_list(lst)] == ["a_1.csv"]
    lst.write_text("/a_1.csv\n/missing_1.csv\n")
    with pytest.raises(ProfileDataError, match=r"missing_1\.csv does not exist"):
        load_profile_list(lst)
    lst.write_text("\n# nothing\n")
    with pytest.raises(ProfileDataError, match="names no profile"):
        load_profile_list(lst)
    with pytest.raises(ProfileDataError, match="cannot read the profile list"):
        load_profile_list(tmp_path / "nope.txt")


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.binary(max_size=300))
def test_fuzzed_files_parse_or_fail_typed(tmp_path, data):
    """Any bytes: a profile of finite points, or ProfileDataError — never another exception."""
    f = tmp_path / "f_1.csv"
    f.write_bytes(data)
    try:
        r = read_profile(f)
    except ProfileDataError:
        return
    assert r.xz.ndim == 2 and r.xz.shape[1] == 2 and len(r.xz) > 0 and np.all(np.isfinite(r.xz))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(xz=st.lists(st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4)), min_size=1, max_size=30))
def test_csv_round_trip(tmp_path, xz):
    f = tmp_path / "r_1.csv"
    f.write_text("".join(f"{x!r},{z!r}\n" for x, z in xz))
    np.testing.assert_array_equal(read_profile(f).xz, np.asarray(xz, dtype=float))


def test_real_lists_read_in_place():
    need_shared(R19 / "train_file.txt")
    tr = load_profile_list(R19 / "train_file.txt")
    va = load_profile_list(R19 / "val_file.txt")
    assert (len(tr), len(va)) == (1392, 348)
    assert all(r.label is not None and len(r) > 100 for r in tr + va)
    # Repeats of one position: same folder and position id, different repeat numbers.
    by_pos: dict[str, set[int]] = {}
    for r in tr:
        by_pos.setdefault(r.position, set()).add(r.repeat)
    assert max(len(v) for v in by_pos.values()) >= 5
    assert {r.side for r in tr} == {-1, 1}
