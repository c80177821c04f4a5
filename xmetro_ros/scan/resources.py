"""Locate packaged data: config files and the shipped default model, in a source tree or an installed package.

Three layouts, looked up in this order:

1. a source checkout (``package.xml`` next to the package): ``<checkout>/config``;
2. the pip route (wheel / ``pip install .``): ``config/`` travels inside the Python package;
3. the colcon route (``colcon build`` in a ROS 2 workspace, CMakeLists.txt): config and the default model are
   installed into ``<prefix>/share/xmetro_ros/`` and found through the ament index: the first prefix of
   ``AMENT_PREFIX_PATH`` holding the marker ``share/ament_index/resource_index/packages/xmetro_ros``.

The ament lookup is written here (a few lines) rather than taken from ``ament_index_python``: that package is not a
dependency of the pip route, and this is all of it that we need (``get_package_share_directory``'s rule; a test
checks both agree where ``ament_index_python`` is installed).
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["PACKAGE", "ament_share_dir", "config_path", "default_model_dir", "package_dir", "pose_model_dir",
           "pose_model_path", "repo_root"]

PACKAGE = "xmetro_ros"


def package_dir() -> Path:
    """Directory of the installed (or checked-out) ``xmetro_ros`` package."""
    return Path(__file__).resolve().parent.parent


def repo_root() -> Path | None:
    """The source checkout holding this package, if running from one (it has package.xml)."""
    root = package_dir().parent
    return root if (root / "package.xml").exists() else None


def ament_share_dir(package: str = PACKAGE, prefix_path: str | None = None) -> Path | None:
    """``<prefix>/share/<package>`` of the first ``AMENT_PREFIX_PATH`` prefix that registers ``package`` in the
    ament resource index (``share/ament_index/resource_index/packages/<package>``); None when none does."""
    value = os.environ.get("AMENT_PREFIX_PATH", "") if prefix_path is None else prefix_path
    for prefix in value.split(os.pathsep):
        if prefix and (Path(prefix) / "share" / "ament_index" / "resource_index" / "packages" / package).is_file():
            return Path(prefix) / "share" / package
    return None


def config_path(name: str) -> Path:
    """Path of ``config/<name>``: the checkout's config/, else the copy in the package, else the ament share dir."""
    candidates = []
    root = repo_root()
    if root is not None:
        candidates.append(root / "config" / name)
    candidates.append(package_dir() / "config" / name)
    share = ament_share_dir()
    if share is not None:
        candidates.append(share / "config" / name)
    for c in candidates:
        if c.exists():
            return c
    raise FileNotFoundError(
        f"config file {name!r} not found (looked in: {', '.join(map(str, candidates))}"
        + ("" if share is not None else f"; no {PACKAGE} in the ament index of AMENT_PREFIX_PATH") + ")")


def _shipped_model_dir(name: str, marker: str = "card.json") -> Path:
    """``models/NAME`` in the package when it holds ``marker`` (a file or directory; '' = the directory itself),
    else under the ament index's share directory when there, else the package path."""
    here = package_dir() / "models" / name
    if (here / marker).exists():
        return here
    share = ament_share_dir()
    if share is not None and (share / "models" / name / marker).exists():
        return share / "models" / name
    return here


def default_model_dir() -> Path:
    """Directory of the shipped default model set (ONNX + card): in the package (checkout, pip route), else
    ``share/xmetro_ros/models/default`` of the ament index (colcon route). When neither exists, the package path
    (the caller reports the model as missing there)."""
    return _shipped_model_dir("default")


def pose_model_dir() -> Path:
    """Directory of the shipped pose model set (trained at the rescan recommender's head orientations: it judges
    scans taken there and the recommender searches with it; docs/services.md, "Two model sets"), found like
    :func:`default_model_dir`."""
    return _shipped_model_dir("posed")


def pose_model_path(model_dir: str | Path | None, pose_model_dir_value: str | Path | None) -> Path | None:
    """The pose model set to load next to the primary ``model_dir`` (the node's ``pose_model_dir`` rule): 'none' →
    None; a path → it; '' or None → the shipped pose model, but only next to the shipped primary (``model_dir`` ''
    or None: a model of one's own is for its own scanner)."""
    v = "" if pose_model_dir_value is None else str(pose_model_dir_value)
    if v.lower() == "none":
        return None
    if v:
        return Path(v)
    return None if model_dir else pose_model_dir()


def search_models_dir() -> Path:
    """Directory of the shipped search ensemble (one sub-directory per pose model set the rescan search consults
    together: ``plan.ensemble_search``), found like :func:`default_model_dir`."""
    return _shipped_model_dir("search", "")


def search_models_path(model_dir: str | Path | None, pose_model_dir_value: str | Path | None,
                       search_models_value: str | Path | None) -> Path | None:
    """The search ensemble to load (the node's ``search_models_dir`` rule): 'none' → None (the search uses the pose
    model, else the primary); a path → it; '' or None → the shipped ensemble, but only next to the shipped primary
    and pose model (both '' or None: models of one's own are searched with as they are)."""
    v = "" if search_models_value is None else str(search_models_value)
    if v.lower() == "none":
        return None
    if v:
        return Path(v)
    return None if (model_dir or pose_model_dir_value) else search_models_dir()
