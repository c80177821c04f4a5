"""Locate packaged data: config files and the shipped default model, in a source tree or an installed package."""

from __future__ import annotations

from pathlib import Path

__all__ = ["config_path", "default_model_dir", "package_dir", "repo_root"]


def package_dir() -> Path:
    """Directory of the installed (or checked-out) ``xmetro_ros`` package."""
    return Path(__file__).resolve().parent


def repo_root() -> Path | None:
    """The source checkout holding this package, if running from one (it has package.xml)."""
    root = package_dir().parent
    return root if (root / "package.xml").exists() else None


def config_path(name: str) -> Path:
    """Path of ``config/<name>``: the checkout's config/ first, else the copy installed in the package."""
    candidates = []
    root = repo_root()
    if root is not None:
        candidates.append(root / "config" / name)
    candidates.append(package_dir() / "config" / name)
    for c in candidates:
        if c.exists():
            return c
    raise FileNotFoundError(f"config file {name!r} not found (looked in: {', '.join(map(str, candidates))})")


def default_model_dir() -> Path:
    """Directory of the shipped default model set (ONNX + card)."""
    return package_dir() / "models" / "default"
