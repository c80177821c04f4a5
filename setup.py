"""pip route: `pip install .` / `pip install -e .` builds our msg/srv with CMake + rosidl against the ROS 2 wheels.

The CMake project (CMakeLists.txt) is configured with XMETRO_PIP_BUILD=ON, built and installed into a staging
prefix under build/. The generated Python modules and typesupport extensions are copied into the package
(xmetro_ros/msg, xmetro_ros/srv, xmetro_ros/*.so; git-ignored); the staged C libraries and share/ files are shipped
as data files, so they land in the environment's lib/ and share/ exactly as the ros-* wheels lay theirs out.

tf2_msgs (the type of /tf and /tf_static) has no wheel: where the build environment has no tf2_msgs of its own, the
upstream definition vendored in vendor/tf2_msgs (its README.md) is built the same way into the same staging prefix,
first, and shipped beside ours (the top-level package tf2_msgs/, git-ignored, plus its libraries and share/ files).
Where a tf2_msgs is installed (a ROS 2 system) it is used and nothing is vendored. XMETRO_VENDOR_TF2_MSGS=1 / 0
forces the vendored build on / off.
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
TF2 = "tf2_msgs"
TF2_SRC = ROOT / "vendor" / TF2
TF2_SOURCES = sorted(str(p.relative_to(ROOT)) for p in TF2_SRC.rglob("*")
                     if p.is_file() and p.name not in ("README.md", "COLCON_IGNORE", "LICENSE"))
INTERFACE_SUBPACKAGES = ("msg", "srv", "action")
#: Written into the tf2_msgs package this package builds and ships: tells it from an installed tf2_msgs.
TF2_MARKER = "XMETRO_VENDORED"


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


def _stamp(sources: list[str]) -> str:
    h = []
    for rel in sources:
        h.append(f"{rel}:{(ROOT / rel).stat().st_mtime_ns}:{(ROOT / rel).stat().st_size}")
    # The interpreter and the ROS 2 install tree built against (the venv, or pip's isolated build environment): not
    # sys.executable as spelt, which differs between `pip` (bin/python3) and `python -m pip` (bin/python) of one venv.
    return "\n".join([*h, os.path.realpath(sys.executable), str(_ros_prefix())])


def vendor_tf2_msgs() -> bool:
    """Whether to build vendor/tf2_msgs: the build environment has no tf2_msgs but one this package shipped before,
    recognised by its marker file (TF2_MARKER: an earlier build's copy in a checkout, found through the current
    directory or an editable install, or the copy a regular install of xmetro_ros put into site-packages) or by lying
    in this checkout. Rebuilding replaces it."""
    forced = os.environ.get("XMETRO_VENDOR_TF2_MSGS", "").strip()
    if forced in ("0", "1"):
        return forced == "1"
    from importlib.util import find_spec

    try:
        spec = find_spec(TF2)
    except (ImportError, ValueError):
        spec = None
    if spec is None:
        return True
    dirs = [Path(d).resolve() for d in spec.submodule_search_locations or []]
    if spec.origin:
        dirs.append(Path(spec.origin).resolve().parent)
    return any(ROOT in d.parents or (d / TF2_MARKER).exists() for d in dirs)


def _build_env() -> dict[str, str]:
    """The environment of a CMake build against the ROS 2 wheels' install tree (and the staging prefix, where
    vendor/tf2_msgs is installed first)."""
    prefix = _ros_prefix()
    stage = ROOT / "build" / "xmetro_stage"
    env = dict(os.environ)
    env["AMENT_PREFIX_PATH"] = os.pathsep.join([str(stage), str(prefix)])
    env["CMAKE_PREFIX_PATH"] = os.pathsep.join([str(stage), str(prefix)])
    env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
    env["LD_LIBRARY_PATH"] = os.pathsep.join(filter(None, [str(stage / "lib"), str(prefix / "lib"),
                                                           env.get("LD_LIBRARY_PATH")]))
    bindir = Path(sys.executable).parent
    env["PATH"] = os.pathsep.join(filter(None, [str(bindir), str(prefix / "bin"), env.get("PATH")]))
    return env


def _cmake_configure_build(src: Path, build: Path, stage: Path, env: dict[str, str], *args: str) -> None:
    shutil.rmtree(build, ignore_errors=True)
    gen = ["-G", "Ninja"] if shutil.which("ninja", path=env["PATH"]) else []
    subprocess.run(
        ["cmake", "-S", str(src), "-B", str(build), *gen, "-DCMAKE_BUILD_TYPE=Release",
         f"-DCMAKE_INSTALL_PREFIX={stage}", "-DBUILD_TESTING=OFF", *args,
         f"-DPython3_EXECUTABLE={sys.executable}", f"-DPYTHON_EXECUTABLE={sys.executable}"],
        check=True, env=env)
    subprocess.run(["cmake", "--build", str(build), "-j", str(os.cpu_count() or 2)], check=True, env=env)


def _copy_generated(generated: Path, dest: Path) -> None:
    """The generated msg/srv/action modules and the typesupport extensions of ``generated`` into the package
    folder ``dest`` (git-ignored there), so that both a regular and an editable install see them."""
    for sub in INTERFACE_SUBPACKAGES:
        shutil.rmtree(dest / sub, ignore_errors=True)
        if (generated / sub).is_dir():
            shutil.copytree(generated / sub, dest / sub, ignore=shutil.ignore_patterns("__pycache__", "*.c"))
    for so in dest.glob("*.so"):
        so.unlink()
    for so in generated.glob("*.so"):
        shutil.copy2(so, dest / so.name)


def build_interfaces() -> Path:
    """Configure, build and install the CMake project into build/xmetro_stage, after vendor/tf2_msgs where it is
    vendored (vendor_tf2_msgs); return the staging prefix.

    Stamps keep an unchanged rebuild fast: ours is rebuilt when its interface files (or the tf2_msgs choice or
    sources) change; vendor/tf2_msgs only when its own files change; otherwise its build tree is merely installed
    again into a fresh stage (a fraction of a second)."""
    build = ROOT / "build" / "xmetro_cmake"
    stage = ROOT / "build" / "xmetro_stage"
    stamp = ROOT / "build" / "xmetro_stage.stamp"
    tf2_build = ROOT / "build" / "tf2_msgs_cmake"
    tf2_stamp = ROOT / "build" / "tf2_msgs_cmake.stamp"
    site = stage / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    generated, tf2_generated = site / PKG, site / TF2
    vendor = vendor_tf2_msgs()
    if vendor and not (TF2_SRC / "package.xml").exists():
        raise RuntimeError(f"tf2_msgs is not installed and {TF2_SRC} is missing: nothing provides tf2_msgs")
    tf2_text = _stamp(TF2_SOURCES) if vendor else "tf2_msgs: installed, not vendored"
    text = "\n".join([_stamp(INTERFACE_SOURCES), tf2_text])
    if not (stamp.exists() and stamp.read_text() == text and generated.exists()
            and (tf2_generated.exists() or not vendor)):
        env = _build_env()
        shutil.rmtree(stage, ignore_errors=True)
        if vendor:
            built = tf2_stamp.exists() and tf2_stamp.read_text() == tf2_text
            if not (built and (tf2_build / "CMakeCache.txt").exists()):
                _cmake_configure_build(TF2_SRC, tf2_build, stage, env)
                tf2_stamp.write_text(tf2_text)
            subprocess.run(["cmake", "--install", str(tf2_build), "--prefix", str(stage)], check=True, env=env)
        _cmake_configure_build(ROOT, build, stage, env, "-DXMETRO_PIP_BUILD=ON")
        subprocess.run(["cmake", "--install", str(build)], check=True, env=env)
        stamp.write_text(text)
    _copy_generated(generated, ROOT / PKG)
    if vendor:
        shutil.rmtree(ROOT / TF2, ignore_errors=True)
        (ROOT / TF2).mkdir()
        shutil.copy2(tf2_generated / "__init__.py", ROOT / TF2 / "__init__.py")
        (ROOT / TF2 / TF2_MARKER).write_text(
            f"Built by xmetro_ros's setup.py from {TF2_SRC.relative_to(ROOT)} (upstream's definitions, see its "
            "README.md)\nbecause no tf2_msgs was installed; an installed tf2_msgs is used instead where present.\n")
        _copy_generated(tf2_generated, ROOT / TF2)
    else:  # an earlier vendored copy would shadow the installed tf2_msgs in the checkout
        shutil.rmtree(ROOT / TF2, ignore_errors=True)
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


def _tf2_packages() -> list[str]:
    """The vendored tf2_msgs packages present in the checkout (none where tf2_msgs is installed)."""
    if not (ROOT / TF2 / "__init__.py").exists():
        return []
    return [TF2, *(f"{TF2}.{sub}" for sub in INTERFACE_SUBPACKAGES if (ROOT / TF2 / sub / "__init__.py").exists())]


class BuildWithInterfaces(build_py):
    """build_py that first builds the ROS 2 interfaces and registers the staged libraries as data files."""

    def run(self) -> None:
        build_interfaces()
        # Re-collect packages and package data now that the generated modules exist. The distribution's list too:
        # the editable install maps the top-level packages it names (tf2_msgs -> the checkout's tf2_msgs/).
        tf2 = _tf2_packages()
        self.packages = sorted(set(self.packages or []) | {f"{PKG}.msg", f"{PKG}.srv", f"{PKG}.action", *tf2})
        self.distribution.packages = sorted(set(self.distribution.packages or []) | set(self.packages))
        if tf2:
            tf2_data = ["*.so", TF2_MARKER, *(f"{sub}/*.py" for sub in INTERFACE_SUBPACKAGES)]
            self.package_data = {**(self.package_data or {}), TF2: tf2_data}
            self.distribution.package_data = {**(self.distribution.package_data or {}), **self.package_data}
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
