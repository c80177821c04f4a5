"""The ROS route as a ROS engineer runs it: `colcon build` and `colcon test` (colcon from PyPI, against the ROS 2
wheels of this environment as the underlay) in a temporary workspace holding this repository's tracked files.

``colcon test`` must run the suite against the *install* (not the checkout), and fail when a test cannot be
collected. CI runs a subset of the suite there (``-k`` through ``PYTEST_ADDOPTS``): the whole suite is `make test`.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: Set by CMakeLists.txt's ament_add_pytest_test: the suite runs under `colcon test`, against this install prefix.
INSTALL_ENV = "XMETRO_TEST_INSTALL_PREFIX"
#: The subset `colcon test` runs here: this file's install check, message round trips (generated interfaces and
#: typesupport libraries of the install), the layer rules, and a node started from the install with a real scan.
SUBSET = "test_colcon or test_scan_io or test_layers or test_node_process_with_params_file"


def test_imports_come_from_the_install():
    """Under `colcon test`: xmetro_ros, its generated messages and its config resolve to the install prefix."""
    prefix = os.environ.get(INSTALL_ENV)
    if not prefix:
        pytest.skip(f"runs under `colcon test` only ({INSTALL_ENV} unset); test_colcon_build_and_test runs it there")
    import xmetro_ros
    import xmetro_ros.msg
    from xmetro_ros.scan.resources import config_path, default_model_dir

    site = Path(os.path.abspath(prefix))
    for f in (xmetro_ros.__file__, xmetro_ros.msg.__file__):  # where Python found them
        assert site in Path(os.path.abspath(f)).parents, f"{f} is not from the install {prefix}"
    # config and model: the install's files (with --symlink-install those link to the sources, hence samefile)
    share = site / "share" / "xmetro_ros"
    assert config_path("xmetro.yaml").samefile(share / "config" / "xmetro.yaml")
    assert (Path(default_model_dir()) / "card.json").samefile(share / "models" / "default" / "card.json")


def _tracked_copy(dest: Path) -> None:
    """The repository's files that git does not ignore (a `git clone`, plus files not yet committed) into ``dest``;
    the working tree less build outputs where there is no git."""
    dest.mkdir(parents=True)
    if (ROOT / ".git").exists() and shutil.which("git"):
        files = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-z", "--cached", "--others",
                                "--exclude-standard"], capture_output=True, check=True
                               ).stdout.decode().split("\0")
        for rel in filter(None, files):
            src = ROOT / rel
            if src.is_file():
                (dest / rel).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(src, dest / rel)
    else:
        shutil.copytree(ROOT, dest, dirs_exist_ok=True, ignore=shutil.ignore_patterns(
            ".venv", "build", "install", "log", "out", "__pycache__", "msg", "srv", "action", "*.so"))


def _colcon_env() -> dict[str, str]:
    """This environment's ROS 2 wheels as the underlay, without the variables of a `colcon test` run itself."""
    from test_packaging import underlay_env

    env = underlay_env()
    env.pop(INSTALL_ENV, None)
    env.pop("PYTEST_ADDOPTS", None)
    return env


def _junit(ws: Path) -> tuple[dict[str, int], dict[str, str]]:
    """Totals and per-test outcome ("passed", "skipped", "failure", "error") of the pytest run's xunit file."""
    (xml,) = (ws / "build" / "xmetro_ros" / "test_results" / "xmetro_ros").glob("*pytest*.xml")
    suite = ET.parse(xml).getroot()
    suite = suite if suite.tag == "testsuite" else suite.find("testsuite")
    assert suite is not None
    totals = {k: int(suite.get(k, 0)) for k in ("tests", "failures", "errors", "skipped")}
    outcome = {}
    for case in suite.iter("testcase"):
        kind = next((c.tag for c in case if c.tag in ("failure", "error", "skipped")), "passed")
        outcome[case.get("name", "")] = kind
    return totals, outcome


@pytest.mark.timeout(1500)
def test_colcon_build_and_test(tmp_path: Path):
    """`colcon build --symlink-install` then `colcon test --return-code-on-test-failure` in a fresh workspace: the
    Python sources are linked into the install, the suite's tests are collected and run from the install (the install
    check passes there, not skipped), and a test file that cannot be collected makes `colcon test` fail."""
    if os.environ.get(INSTALL_ENV):
        pytest.skip("already running under `colcon test`")
    if shutil.which("colcon", path=_colcon_env()["PATH"]) is None:
        pytest.fail("colcon is not installed: `make setup` installs colcon-common-extensions "
                    "(tools/build-requirements.txt)")
    ws = tmp_path / "ws"
    _tracked_copy(ws / "src" / "xmetro_ros")
    # The real data sits beside the repository (../shared): beside the package's copy too, so the tests that read
    # it run under colcon as in the checkout; colcon looks for packages in the package's folder only.
    if (ROOT.parent / "shared").exists():
        (ws / "src" / "shared").symlink_to(ROOT.parent / "shared")
    crawl = ["--base-paths", str(ws / "src" / "xmetro_ros")]
    env = _colcon_env()
    colcon = shutil.which("colcon", path=env["PATH"])
    assert colcon is not None
    # --symlink-install, as ROS developers build (test_packaging's CMake install covers the copying layout).
    build = subprocess.run([colcon, "build", *crawl, "--symlink-install", "--event-handlers", "console_direct-",
                            "--cmake-args", f"-DPython3_EXECUTABLE={sys.executable}", "-DBUILD_TESTING=ON"],
                           cwd=ws, env=env, capture_output=True, text=True, timeout=900)
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    assert (ws / "install" / "xmetro_ros" / "share" / "xmetro_ros" / "package.xml").is_file()
    site = ws / "install" / "xmetro_ros" / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / \
        "site-packages" / "xmetro_ros"
    src = ws / "src" / "xmetro_ros" / "xmetro_ros"
    for rel in ("__init__.py", "ros/node.py", "judge/scan_handler.py"):  # Python sources linked, not copied
        assert (site / rel).is_symlink() and (site / rel).resolve() == (src / rel).resolve(), rel
    assert (site / "msg" / "__init__.py").is_file() and not (site / "models").exists()

    # No `source install/setup.bash` on purpose: the registered test must find the install by itself.
    run_env = dict(env, PYTEST_ADDOPTS=f"-k '{SUBSET}'")
    test = subprocess.run([colcon, "test", *crawl, "--return-code-on-test-failure", "--event-handlers",
                           "console_direct-"],
                          cwd=ws, env=run_env, capture_output=True, text=True, timeout=900)
    log = (ws / "build" / "xmetro_ros" / "ament_cmake_pytest" / "xmetro_ros_pytest.txt")
    detail = (log.read_text()[-4000:] if log.exists() else "") + test.stderr[-2000:]
    assert test.returncode == 0, detail
    totals, outcome = _junit(ws)
    assert totals["errors"] == 0 and totals["failures"] == 0, (totals, detail)
    assert totals["tests"] - totals["skipped"] >= 10, (totals, detail)
    assert outcome.get("test_imports_come_from_the_install") == "passed", (outcome, detail)
    assert outcome.get("test_node_process_with_params_file") == "passed", (outcome, detail)

    # A test module that cannot be imported: collection fails, so does `colcon test` (not exit 0 with nothing run).
    (ws / "src" / "xmetro_ros" / "test" / "test_zz_uncollectable.py").write_text("import no_such_module_xmetro\n")
    broken = subprocess.run([colcon, "test", *crawl, "--return-code-on-test-failure", "--event-handlers",
                             "console_direct-"],
                            cwd=ws, env=dict(env, PYTEST_ADDOPTS="-k test_imports_come_from_the_install"),
                            capture_output=True, text=True, timeout=600)
    assert broken.returncode != 0, broken.stdout[-2000:]
    assert "no_such_module_xmetro" in log.read_text()
