"""pip route: `pip install .` / `pip install -e .` builds our msg/srv with CMake + rosidl against the ROS 2 wheels.

The CMake project (CMakeLists.txt) is configured with XMETRO_PIP_BUILD=ON, built and installed into a staging
prefix under build/. The generated Python modules and typesupport extensions are copied into the package
(xmetro_ros/msg, xmetro_ros/srv, xmetro_ros/*.so; git-ignored); the staged C libraries and share/ files are shipped
as data files, so they land in the environment's lib/ and share/ exactly as the ros-* wheels lay theirs out.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from distutils.command.install_data import install_data
from pathlib import Path

from setuptools import Distribution, setup
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent
PKG = "xmetro_ros"
INTERFACE_SOURCES = ["CMakeLists.txt", "package.xml", *sorted(str(p.relative_to(ROOT)) for p in
                     [*ROOT.glob("msg/*.msg"), *ROOT.glob("srv/*.srv"), *ROOT.glob("action/*.action")])]


def package_version() -> str:
    """The version, from package.xml (the one source: colcon and rosdep read it there)."""
    import re

    m = re.search(r"<version>\s*([^<\s]+)\s*</version>", (ROOT / "package.xml").read_text())
    if m is None:
        raise RuntimeError("package.xml has no <version>")
    return m.group(1)


def _ros_prefix() -> Path:
    """The prefix holding the ROS 2 wheels' install tree (the venv, or pip's isolated build environment)."""
    import rosidl_generator_py

    return Path(rosidl_generator_py.__file__).resolve().parents[4]


def _stamp() -> str:
    h = []
    for rel in INTERFACE_SOURCES:
        h.append(f"{rel}:{(ROOT / rel).stat().st_mtime_ns}:{(ROOT / rel).stat().st_size}")
    return "\n".join([*h, sys.executable])


def build_interfaces() -> Path:
    """Configure, build and install the CMake project into build/xmetro_stage; return the staging prefix."""
    build = ROOT / "build" / "xmetro_cmake"
    stage = ROOT / "build" / "xmetro_stage"
    stamp = ROOT / "build" / "xmetro_stage.stamp"
    pyver = f"python{sys.version_info.major}.{sys.version_info.minor}"
    generated = stage / "lib" / pyver / "site-packages" / PKG
    if not (stamp.exists() and stamp.read_text() == _stamp() and generated.exists()):
        prefix = _ros_prefix()
        env = dict(os.environ)
        env["AMENT_PREFIX_PATH"] = str(prefix)
        env["CMAKE_PREFIX_PATH"] = str(prefix)
        env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
        env["LD_LIBRARY_PATH"] = os.pathsep.join(filter(None, [str(prefix / "lib"), env.get("LD_LIBRARY_PATH")]))
        bindir = Path(sys.executable).parent
        env["PATH"] = os.pathsep.join(filter(None, [str(bindir), str(prefix / "bin"), env.get("PATH")]))
        shutil.rmtree(build, ignore_errors=True)
        shutil.rmtree(stage, ignore_errors=True)
        gen = ["-G", "Ninja"] if shutil.which("ninja", path=env["PATH"]) else []
        subprocess.run(
            ["cmake", "-S", str(ROOT), "-B", str(build), *gen, "-DCMAKE_BUILD_TYPE=Release",
             f"-DCMAKE_INSTALL_PREFIX={stage}", "-DXMETRO_PIP_BUILD=ON", "-DBUILD_TESTING=OFF",
             f"-DPython3_EXECUTABLE={sys.executable}", f"-DPYTHON_EXECUTABLE={sys.executable}"],
            check=True, env=env)
        subprocess.run(["cmake", "--build", str(build), "-j", str(os.cpu_count() or 2)], check=True, env=env)
        subprocess.run(["cmake", "--install", str(build)], check=True, env=env)
        stamp.write_text(_stamp())
    # Generated Python modules and typesupport extensions go into the source package (git-ignored), so that both
    # a regular and an editable install see them.
    for sub in ("msg", "srv", "action"):
        shutil.rmtree(ROOT / PKG / sub, ignore_errors=True)
        shutil.copytree(generated / sub, ROOT / PKG / sub)
    for so in ROOT.joinpath(PKG).glob("*.so"):
        so.unlink()
    for so in generated.glob("*.so"):
        shutil.copy2(so, ROOT / PKG / so.name)
    # The config directory travels inside the package for non-checkout installs (resources.config_path).
    shutil.rmtree(ROOT / PKG / "config", ignore_errors=True)
    shutil.copytree(ROOT / "config", ROOT / PKG / "config")
    return stage


def _data_files(stage: Path) -> list[tuple[str, list[str]]]:
    out: dict[str, list[str]] = {}
    for f in sorted((stage / "lib").glob("lib*.so*")):
        out.setdefault("lib", []).append(str(f))
    for f in sorted((stage / "share").rglob("*")):
        if f.is_file():
            out.setdefault(str(f.parent.relative_to(stage)), []).append(str(f))
    return sorted(out.items())


class BuildWithInterfaces(build_py):
    """build_py that first builds the ROS 2 interfaces and registers the staged libraries as data files."""

    def run(self) -> None:
        build_interfaces()
        # Re-collect package data now that the generated modules exist.
        self.packages = sorted(set(self.packages or []) | {f"{PKG}.msg", f"{PKG}.srv", f"{PKG}.action"})
        self.data_files = self._get_data_files()
        super().run()


class InstallDataWithInterfaces(install_data):
    """install_data that ships the staged libraries and share/ files (known only once the interfaces are built)."""

    def run(self) -> None:
        self.data_files = _data_files(build_interfaces())
        super().run()


class InterfaceDistribution(Distribution):
    # The staged libraries are data files known only after the build, so both checks must say yes: setuptools'
    # editable install asks has_data(), `install` (inside the wheel build of `pip install .`) asks
    # has_data_files(); either one saying no silently leaves lib*.so out and the messages fail to import.
    def has_data(self) -> bool:
        return True

    def has_data_files(self) -> bool:
        return True


setup(
    version=package_version(),
    distclass=InterfaceDistribution,
    cmdclass={"build_py": BuildWithInterfaces, "install_data": InstallDataWithInterfaces},
)
