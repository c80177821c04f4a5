"""The ROS boundary, enforced (docs/architecture.md, "Layers"); which package may import which is
test/test_import_graph.py's, from the packages' docstrings.

- core: every module of ``xmetro_ros`` outside ``ros/``, ``apps/``, ``msg/`` and ``srv/``: no ROS at all (no rclpy,
  no message packages, no ``xmetro_ros.ros`` / ``apps`` / ``msg`` / ``srv``), not even inside a function; the one
  exception is ``bag/codec.py`` (message objects ⇄ CDR with ``rclpy.serialization``, imported on demand).
- ``ros/``: ROS message types and DDS; ``apps/``: the command-line tools.

Checked statically (every import statement, at any depth, relative ones resolved) and at run time (a fresh
interpreter that imports every core module has no ROS module loaded; ``xmetro predict`` runs without DDS).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from import_graph import import_statements

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "xmetro_ros"
GENERATED = {"msg", "srv", "action"}
LAYERS = ("ros", "apps")
# Core modules allowed to import these (module path relative to the package → allowed import prefixes).
CORE_EXCEPTIONS = {"bag/codec.py": ("rclpy.serialization",)}


def _is_ros(name: str) -> bool:
    """A ROS module (client library, middleware, generated interfaces) by its dotted name."""
    top = name.split(".")[0]
    return (top in {"rclpy", "rosidl_runtime_py", "rpyutils", "launch", "launch_ros", "ament_index_python",
                    "sensor_msgs_py", "message_filters", "tf2_ros"}
            or top.startswith(("rcl", "rmw", "rosidl")) or top.endswith(("_msgs", "_srvs", "_interfaces")))


def _module_of(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, absolute dotted name) of every import in ``path`` (any depth; ``from a import b`` gives a.b too)."""
    out = []
    for line, mod, names in import_statements(path, _module_of(path)):
        out.append((line, mod))
        out += [(line, f"{mod}.{n}") for n in names]
    return out


def _layer(path: Path) -> str:
    rel = path.relative_to(PKG).parts
    if rel[0] in GENERATED:
        return "generated"
    return rel[0] if rel[0] in LAYERS else "core"


def _sources() -> list[Path]:
    return sorted(p for p in PKG.rglob("*.py") if _layer(p) != "generated")


def _violations() -> list[str]:
    bad = []
    for path in _sources():
        layer = _layer(path)
        rel = str(path.relative_to(PKG))
        for line, name in _imports(path):
            where = f"{rel}:{line} imports {name}"
            inner = name.split(".")[1] if name.startswith("xmetro_ros.") else ""
            if layer == "core":
                allowed = CORE_EXCEPTIONS.get(rel, ())
                if (_is_ros(name) and not name.startswith(allowed)) or inner in (*LAYERS, *GENERATED):
                    bad.append(f"core {where}")
    return bad


def test_core_imports_no_ros_and_ros_no_tools():
    assert _violations() == []


def test_layer_check_catches_a_violation(tmp_path, monkeypatch):
    """The check is real: a core module importing rclpy inside a function, or the ROS layer, is reported."""
    fake = tmp_path / "xmetro_ros"
    (fake / "ros").mkdir(parents=True)
    (fake / "__init__.py").write_text("")
    (fake / "ros" / "__init__.py").write_text("")
    (fake / "scan").mkdir()
    (fake / "scan" / "geometry.py").write_text("def f():\n    from rclpy.node import Node\n    return Node\n")
    (fake / "features.py").write_text("from .ros import cloud\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    monkeypatch.setattr(sys.modules[__name__], "PKG", fake)
    found = _violations()
    assert any(v.startswith("core scan/geometry.py:2 imports rclpy.node") for v in found), found
    assert any(v.startswith("core features.py:1 imports xmetro_ros.ros") for v in found), found


def _run(code: str) -> str:
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout.strip().splitlines()[-1]


def test_importing_the_whole_core_loads_no_ros():
    names = [_module_of(p) for p in _sources() if _layer(p) == "core"]
    assert len(names) > 40
    code = (
        "import importlib, sys\n"
        f"for n in {names!r}: importlib.import_module(n)\n"
        "ros = [k for k in sys.modules if k.split('.')[0] in ('rclpy', 'sensor_msgs', 'std_msgs', 'geometry_msgs',\n"
        "       'builtin_interfaces', 'rcl_interfaces', 'diagnostic_msgs', 'xmetro_ros.msg')\n"
        "       or k.startswith(('xmetro_ros.ros', 'xmetro_ros.apps', 'xmetro_ros.msg', 'xmetro_ros.srv',\n"
        "                        'xmetro_ros.action'))]\n"
        "print(sorted(ros))\n"
    )
    assert _run(code) == "[]"


def _run_offline(*commands: list[str]) -> str:
    """Run ``xmetro`` sub-commands in a fresh interpreter with ``rclpy.init`` made to fail (each must exit 0); the
    last line printed lists the DDS-side modules they loaded (``[]``: none)."""
    code = (
        "import sys, rclpy\n"
        "def _no(*a, **k): raise AssertionError('rclpy.init called by an offline tool')\n"
        "rclpy.init = _no\n"
        "from xmetro_ros.apps.cli import main\n"
        f"for argv in {[list(c) for c in commands]!r}:\n"
        "    rc = main(argv)\n"
        "    assert rc == 0, (argv[0], rc)\n"
        "print(sorted(k for k in ('rclpy.node', 'rclpy.executors', 'xmetro_ros.apps.replay', 'xmetro_ros.ros.node')\n"
        "             if k in sys.modules))\n"
    )
    return _run(code)


@pytest.mark.parametrize("bag", ["demo.mcap"])
def test_offline_predict_creates_no_dds_participant(tmp_path, bag):
    """``xmetro predict`` never starts DDS: rclpy.init is made to fail, rclpy.node / the replay tool stay unloaded."""
    assert _run_offline(["predict", str(ROOT / "bags" / bag), "--out", str(tmp_path / "out.mcap")]) == "[]"
    assert (tmp_path / "out.mcap").stat().st_size > 0


def test_offline_simulate_and_loop_create_no_dds_participant(tmp_path):
    """``xmetro simulate`` and ``xmetro loop`` (reading the bag it wrote) never start DDS either."""
    sim, loop = tmp_path / "sim", tmp_path / "loop"
    assert _run_offline(
        ["simulate", "--quick", "--artifact", "sphere:radius=12.5", "--artifact", "sphere:radius=12.5",
         "--out", str(sim)],
        ["loop", str(sim / "campaign.mcap"), "--artifact", "sphere:radius=12.5", "--max-iter", "1", "--n-perm", "20",
         "--iterations", "50", "--out", str(loop)]) == "[]"
    assert (loop / "report.json").stat().st_size > 0


def test_every_package_import_resolves():
    """Imports of our own modules (also lazy ones inside functions, which only fail when that path runs) name
    modules that exist."""
    def exists(mod: str) -> bool:
        rel = Path(*mod.split("."))
        return (ROOT / rel).with_suffix(".py").exists() or (ROOT / rel / "__init__.py").exists() \
            or mod.split(".")[1:2] in (["msg"], ["srv"], ["action"])
    bad = []
    for path in _sources():
        for line, name in _imports(path):
            if not name.startswith("xmetro_ros"):
                continue
            parent = name.rpartition(".")[0]
            # `from a.b import c`: a.b must be a module; c a module or a name in it (checked when it is a module)
            if not exists(name) and not exists(parent):
                bad.append(f"{path.relative_to(PKG)}:{line} imports {name}")
    assert bad == []


def test_lint_runs_mypy_and_mypy_fails_on_a_type_error(tmp_path):
    """`make lint` runs mypy with the project's configuration, which rejects a type error in our package."""
    recipe = subprocess.run(["make", "-n", "lint"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert "ruff check" in recipe.stdout and "mypy" in recipe.stdout, recipe.stdout
    bad = tmp_path / "xmetro_typo.py"
    bad.write_text("def f() -> int:\n    return 'not an int'\n")
    out = subprocess.run([sys.executable, "-m", "mypy", "--config-file", str(ROOT / "pyproject.toml"), str(bad)],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert out.returncode != 0 and "Incompatible return value type" in out.stdout, out.stdout
