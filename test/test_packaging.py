"""The regular (non-editable) install: the wheel that `pip install .` builds carries everything a fresh environment
needs — the generated message modules, the typesupport extensions, the C libraries they load (as data files into
the environment's lib/), the ament index and interface files, the config and the default model.

(A full `pip install .` into a fresh venv, with build isolation and the ROS 2 wheels from the registry, takes ~95 s
here and is described in README/docs/architecture.md; this test checks the same wheel, built against the dev
environment's build requirements, in seconds.)
"""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.timeout(600)
def test_wheel_carries_interfaces_libraries_config_and_model(tmp_path: Path):
    out = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                          "-w", str(tmp_path), str(ROOT)], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    (wheel,) = tmp_path.glob("xmetro_ros-*.whl")
    assert wheel.name.startswith(f"xmetro_ros-{_package_xml_version()}-"), wheel.name
    names = set(zipfile.ZipFile(wheel).namelist())
    for layer in ("xmetro_ros/ros/node.py", "xmetro_ros/ros/core.py", "xmetro_ros/apps/cli.py",
                  "xmetro_ros/bag/codec.py", "xmetro_ros/sim/scanner_sim.py", "xmetro_ros/learn/train.py",
                  "xmetro_ros/loop/run.py"):
        assert layer in names, layer
    data = next((n.split("/")[0] for n in names if n.endswith(".data/data/lib/libxmetro_ros__rosidl_generator_py.so")),
                None)
    assert data, "the wheel has no lib/ data files: the interface libraries would be missing after install"
    for lib in ("rosidl_generator_c", "rosidl_generator_py", "rosidl_typesupport_c", "rosidl_typesupport_fastrtps_c",
                "rosidl_typesupport_introspection_c", "rosidl_typesupport_cpp"):
        assert f"{data}/data/lib/libxmetro_ros__{lib}.so" in names, lib
    for ext in ("rosidl_typesupport_c", "rosidl_typesupport_fastrtps_c", "rosidl_typesupport_introspection_c"):
        assert any(n.startswith(f"xmetro_ros/xmetro_ros_s__{ext}") and n.endswith(".so") for n in names), ext
    for must in ("xmetro_ros/msg/_scan_quality.py", "xmetro_ros/msg/_scanner_settings.py", "xmetro_ros/srv/_explain.py",
                 "xmetro_ros/srv/_recommend_settings.py", "xmetro_ros/models/default/card.json",
                 "xmetro_ros/config/xmetro.yaml", "xmetro_ros/config/fastdds_localhost.xml",
                 f"{data}/data/share/ament_index/resource_index/packages/xmetro_ros",
                 f"{data}/data/share/xmetro_ros/msg/ScanQuality.msg",
                 "xmetro_ros/action/_recommend_settings.py", "xmetro_ros/ros/lifecycle_node.py",
                 f"{data}/data/share/xmetro_ros/action/RecommendSettings.action"):
        assert must in names, must
    assert any(n.startswith("xmetro_ros/models/default/") and n.endswith(".onnx") for n in names)
    # Runtime install lean: PyTorch and the other training-only packages only under the [train] extra.
    meta = next(n for n in names if n.endswith(".dist-info/METADATA"))
    requires = [ln.split(":", 1)[1].strip() for ln in zipfile.ZipFile(wheel).read(meta).decode().splitlines()
                if ln.startswith("Requires-Dist:")]
    runtime = [r for r in requires if "extra ==" not in r]
    train = [r for r in requires if "extra == \"train\"" in r]
    for heavy in ("torch", "catboost", "shap", "scikit-learn", "open3d", "matplotlib", "skl2onnx"):
        assert not any(r.split(";")[0].strip().startswith(heavy) for r in runtime), (heavy, runtime)
        assert any(r.startswith(heavy) for r in train), (heavy, train)
    for ros in ("ros-rclpy", "ros-action-msgs", "ros-lifecycle-msgs", "onnxruntime"):
        assert any(r.startswith(ros) for r in runtime), (ros, runtime)


def _package_xml_version() -> str:
    import re

    m = re.search(r"<version>\s*([^<\s]+)\s*</version>", (ROOT / "package.xml").read_text())
    assert m, "package.xml has no <version>"
    return m.group(1)


def test_one_version_everywhere():
    """package.xml is the one source: the installed distribution and ``xmetro_ros.__version__`` follow it, and the
    CHANGELOG has an entry for it."""
    from importlib.metadata import version

    import xmetro_ros

    v = _package_xml_version()
    assert xmetro_ros.__version__ == v
    assert version("xmetro_ros") == v
    assert f"## {v}" in (ROOT / "CHANGELOG.md").read_text()
