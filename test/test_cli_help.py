"""What a user reads from the command line (issue 27): help for every option of every command, descriptions without
docstring markup, ``--version``, errors on stderr."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from xmetro_ros import __version__
from xmetro_ros.apps.cli import build_parser, main, plain_text


def _parsers(parser: argparse.ArgumentParser, name: str = "xmetro"):
    yield name, parser
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            for n, sp in a.choices.items():
                yield from _parsers(sp, f"{name} {n}")


def test_every_option_of_every_command_has_help():
    missing = [(name, a.option_strings or a.dest) for name, p in _parsers(build_parser()) for a in p._actions
               if a.dest != "help" and not isinstance(a, argparse._SubParsersAction)
               and (not a.help or a.help == argparse.SUPPRESS)]
    assert not missing, missing


def test_descriptions_read_as_text():
    for name, p in _parsers(build_parser()):
        text = p.format_help()
        assert ":class:" not in text and ":mod:" not in text and "``" not in text, name
    top = build_parser().format_help()
    assert "register(subparsers)" not in top and "laser line scanner" in top


def test_plain_text():
    assert plain_text("see :class:`~xmetro_ros.ros.node.XmetroCore` and ``x``") == "see XmetroCore and `x`"
    assert plain_text(":mod:`xmetro_ros.apps`") == "xmetro_ros.apps"
    assert plain_text(None) is None


def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == f"xmetro {__version__}"


@pytest.mark.parametrize("argv, match", [
    (["calibrate", "no_such_campaign.yaml", "--out", "{tmp}/o"], "xmetro calibrate: error"),
    (["real-data", "--data", "{tmp}", "--out", "{tmp}/o"], "xmetro real-data: error"),
    (["predict", "{tmp}/no_such.mcap", "--out", "{tmp}/o.mcap"], "error"),
    (["loop", "{tmp}/no_such.txt", "--artifact", "sphere:radius=10", "--out", "{tmp}/o"], "does not exist"),
])
def test_errors_go_to_stderr(tmp_path, capsys, argv, match):
    """A failed command exits non-zero (predict: 1, the others: 2, as documented) with the reason on stderr."""
    rc = main([a.replace("{tmp}", str(tmp_path)) for a in argv])
    cap = capsys.readouterr()
    assert rc == (1 if argv[0] == "predict" else 2) and match in cap.err and "error" not in cap.out.lower()


def test_node_help_prints_help_and_starts_no_node(capsys):
    """`xmetro_node --help`: the usage and every parameter, exit 0, rclpy never initialised."""
    import rclpy

    from xmetro_ros.ros.node import main as node_main
    from xmetro_ros.ros.params import PARAMS

    assert node_main(["xmetro_node", "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: xmetro_node") and all(f"  {p.name} = " in out for p in PARAMS)
    assert not rclpy.ok()


def test_training_warnings_are_summarised_once_per_kind():
    """`xmetro train` prints one line per kind of library warning, not one per fit (issue 27)."""
    import warnings

    from sklearn.exceptions import ConvergenceWarning

    from xmetro_ros.apps.train import warning_summary

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(50):
            warnings.warn("Stochastic Optimizer: Maximum iterations (200) reached", ConvergenceWarning, stacklevel=1)
        warnings.warn("something else", UserWarning, stacklevel=1)
    lines = warning_summary(list(caught))
    assert lines == ["ConvergenceWarning x50: Stochastic Optimizer: Maximum iterations (200) reached",
                     "UserWarning x1: something else"]


def test_recommended_orientation_reads_as_axis_angle_and_tilts():
    """The demo's recommendation names the rotation's axis in the head frame and the tilt / turn angles the
    recommender searched (Rz·Ry·Rx), not a bare quaternion (issue 27)."""
    from types import SimpleNamespace

    from scipy.spatial.transform import Rotation

    from xmetro_ros.apps.demo import _quat_deg
    from xmetro_ros.scan.geometry import rotation_xyz

    x, y, z, w = Rotation.from_matrix(rotation_xyz(np.radians(10), np.radians(-15), np.radians(-90))).as_quat()
    text = _quat_deg(SimpleNamespace(x=x, y=y, z=z, w=w))
    assert "tilt 10.0° about X, -15.0° about Y, turn -90.0° about Z" in text and "head frame" in text
    x, y, z, w = Rotation.from_matrix(rotation_xyz(0.0, 0.0, np.radians(90))).as_quat()
    assert "axis (0.00, 0.00, 1.00)" in _quat_deg(SimpleNamespace(x=x, y=y, z=z, w=w))
    assert _quat_deg(SimpleNamespace(x=0.0, y=0.0, z=0.0, w=1.0)) == "keep the current head orientation"
