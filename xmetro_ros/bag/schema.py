"""ROS 2 interface lookup for bags: ``ros2msg`` schema text with dependencies, RIHS01 type hashes, classes.

rosbag2's MCAP storage writes, for a type ``pkg/msg/Type``, a schema named ``pkg/msg/Type`` with encoding
``ros2msg`` whose text is the type's ``.msg`` file followed, for every dependency (depth first, each package's
dependencies in sorted order, each type once), by ``"\\n" + "=" * 80 + "\\nMSG: dep_pkg/DepType\\n"`` and the
dependency's ``.msg`` text. The ``.msg`` and ``.json`` (type description with RIHS01 hashes) files come from
``share/<pkg>/msg`` of the installed interface packages (the ROS wheels install them into the venv prefix; our
own messages land in ``<venv>/share/xmetro_ros/msg``).
"""

from __future__ import annotations

import functools
import json
import os
import re
import sys
from pathlib import Path
from typing import Any

__all__ = [
    "SEPARATOR",
    "UnknownTypeError",
    "msg_dependencies",
    "msg_file",
    "normalize_type",
    "schema_text",
    "share_dirs",
    "type_hash",
]

SEPARATOR = "=" * 80

# Primitive and built-in field types of the .msg language (not dependencies).
_PRIMITIVES = {
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64",
    "uint64", "string", "wstring",
}
_ARRAY_OR_BOUND = re.compile(r"(\[[^\]]*\])|(<=\d+)")


class UnknownTypeError(LookupError):
    """A message type whose definition or Python class is not installed in this environment."""


def normalize_type(type_name: str) -> tuple[str, str, str]:
    """``pkg/msg/Type`` or ``pkg/Type`` → (pkg, "msg", Type). Raises UnknownTypeError on a malformed name."""
    parts = type_name.strip().split("/")
    if len(parts) == 3 and all(parts):
        return parts[0], parts[1], parts[2]
    if len(parts) == 2 and all(parts):
        return parts[0], "msg", parts[1]
    raise UnknownTypeError(f"malformed ROS type name {type_name!r} (expected 'pkg/msg/Type')")


@functools.lru_cache(maxsize=1)
def share_dirs() -> tuple[Path, ...]:
    """Install-space ``share`` directories searched for interfaces: AMENT_PREFIX_PATH entries, then sys.prefix."""
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes += [sys.prefix, sys.base_prefix]
    out: list[Path] = []
    for p in prefixes:
        d = Path(p) / "share"
        if d.is_dir() and d not in out:
            out.append(d)
    return tuple(out)


def _interface_file(type_name: str, ext: str) -> Path:
    pkg, sub, name = normalize_type(type_name)
    for share in share_dirs():
        f = share / pkg / sub / f"{name}.{ext}"
        if f.is_file():
            return f
    raise UnknownTypeError(f"no {name}.{ext} for {pkg}/{sub}/{name} in {[str(s) for s in share_dirs()]}")


def msg_file(type_name: str) -> Path:
    """Path of the installed ``.msg`` file of ``type_name``."""
    return _interface_file(type_name, "msg")


@functools.cache
def _msg_text(type_name: str) -> str:
    return msg_file(type_name).read_text()


def msg_dependencies(pkg: str, text: str) -> list[str]:
    """Sorted unique ``dep_pkg/Type`` names that the ``.msg`` text of a type in package ``pkg`` refers to."""
    deps: set[str] = set()
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        tokens = line.split()
        if len(tokens) < 2:
            continue
        ftype = _ARRAY_OR_BOUND.sub("", tokens[0])
        if ftype in _PRIMITIVES or "=" in tokens[1] or (len(tokens) > 2 and tokens[2].startswith("=")):
            # primitives, and constants (which are always primitive)
            continue
        if "/" in ftype:
            parts = ftype.split("/")
            deps.add(f"{parts[0]}/{parts[-1]}")
        elif ftype == "Header":
            deps.add("std_msgs/Header")
        else:
            deps.add(f"{pkg}/{ftype}")
    return sorted(deps)


@functools.cache
def schema_text(type_name: str) -> str:
    """rosbag2's ``ros2msg`` schema text of ``type_name`` (the .msg followed by its dependency definitions)."""
    pkg, _sub, name = normalize_type(type_name)
    seen: set[str] = set()

    def full(dep_pkg: str, dep_name: str) -> str:
        text = _msg_text(f"{dep_pkg}/msg/{dep_name}")
        out = text
        for dep in msg_dependencies(dep_pkg, text):
            if dep in seen:
                continue
            seen.add(dep)
            dpkg, dname = dep.split("/")
            out += "\n" + SEPARATOR + "\nMSG: " + dep + "\n" + full(dpkg, dname)
        return out

    return full(pkg, name)


@functools.cache
def type_hash(type_name: str) -> str:
    """RIHS01 type hash of ``type_name`` from its installed type description JSON; "" when not installed."""
    pkg, sub, name = normalize_type(type_name)
    try:
        data = json.loads(_interface_file(type_name, "json").read_text())
    except (UnknownTypeError, OSError, ValueError):
        return ""
    for entry in data.get("type_hashes", []):
        if entry.get("type_name") == f"{pkg}/{sub}/{name}":
            return str(entry.get("hash_string", ""))
    return ""


def full_type_name(type_name: str) -> str:
    """``pkg/Type`` or ``pkg/msg/Type`` → ``pkg/msg/Type``."""
    return "/".join(normalize_type(type_name))


def type_name_of(msg: Any) -> str:
    """``pkg/msg/Type`` of an rclpy message instance (or class)."""
    cls = msg if isinstance(msg, type) else type(msg)
    module = cls.__module__.split(".")  # e.g. sensor_msgs.msg._point_cloud2
    return f"{module[0]}/{module[1]}/{cls.__name__}"
