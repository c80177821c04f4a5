"""The shipped Foxglove layout (config/foxglove/xmetro_layout.json) and RViz config (config/rviz/xmetro.rviz), issue
27: they show ~/deviations coloured by |d|, U and the flags, the verdict (ScanQuality) and /diagnostics, and fit the
node's outputs as a bag holds them — every topic they name is in the bag with the schema the panel needs, every
colour field is one of that cloud's PointFields, every message path a field of the message, the frames the clouds'
``header.frame_id``.

`viz_problems` checks a bag; here against the shipped goldens (`xmetro predict`'s outputs of bags/demo.mcap: the
clouds and ScanQuality, no /diagnostics), and in test_demo.py against the demo's own output bag (everything,
/diagnostics included: the node's recording), so that the demo is not run twice.
"""

from __future__ import annotations

import fnmatch
import json
import re
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[1]
LAYOUT = ROOT / "config" / "foxglove" / "xmetro_layout.json"
RVIZ = ROOT / "config" / "rviz" / "xmetro.rviz"
CLOUD = "sensor_msgs/msg/PointCloud2"
QUALITY = "xmetro_ros/msg/ScanQuality"
DIAGNOSTICS = "diagnostic_msgs/msg/DiagnosticArray"
#: Foxglove panel type (the part of a panel id before "!") → the schema of the topic it reads.
PANEL_SCHEMA = {"3D": CLOUD, "RawMessages": QUALITY, "Plot": QUALITY, "StateTransitions": QUALITY,
                "DiagnosticSummary": DIAGNOSTICS, "DiagnosticStatusPanel": DIAGNOSTICS}


def load_layout() -> dict[str, Any]:
    return json.loads(LAYOUT.read_text(encoding="utf-8"))


def load_rviz() -> dict[str, Any]:
    return yaml.safe_load(RVIZ.read_text(encoding="utf-8"))


def _layout_leaves(node: Any) -> list[str]:
    if isinstance(node, str):
        return [node]
    assert isinstance(node, dict) and {"first", "second", "direction"} <= set(node), node
    assert node["direction"] in ("row", "column"), node
    return _layout_leaves(node["first"]) + _layout_leaves(node["second"])


def cloud_displays() -> list[dict[str, Any]]:
    return [d for d in load_rviz()["Visualization Manager"]["Displays"]
            if d["Class"] == "rviz_default_plugins/PointCloud2"]


def references() -> list[tuple[str, str, str, str]]:
    """(where, topic, schema, what it reads there: a PointField, a message path or '') for both configs."""
    refs = []
    for pid, cfg in load_layout()["configById"].items():
        kind = pid.split("!")[0]
        schema = PANEL_SCHEMA[kind]
        if kind == "3D":
            refs += [(f"{pid} topics", t, schema, s.get("colorField", "")) for t, s in cfg["topics"].items()]
        elif kind == "RawMessages":
            topic, _, path = cfg["topicPath"].partition(".")
            refs.append((f"{pid} topicPath", topic, schema, path))
        elif kind in ("Plot", "StateTransitions"):
            for p in cfg["paths"]:
                topic, _, path = p["value"].partition(".")
                refs.append((f"{pid} paths", topic, schema, path))
        else:
            refs.append((f"{pid} topicToRender", cfg["topicToRender"], schema, ""))
    refs += [(f"rviz {d['Name']}", d["Topic"]["Value"], CLOUD, d["Channel Name"]) for d in cloud_displays()]
    return refs


def _message_field(schema: str, path: str) -> bool:
    """Whether ``path`` (a.b.c, no indices) names a field of the ROS message ``schema``."""
    import importlib

    pkg, _, name = schema.split("/")
    cls = getattr(importlib.import_module(f"{pkg}.msg"), name)
    for part in path.split("."):
        fields = cls.get_fields_and_field_types()
        if part not in fields:
            return False
        t = fields[part]
        if "/" in t and not t.startswith("sequence"):
            p, n = t.split("/")
            cls = getattr(importlib.import_module(f"{p}.msg"), n)
    return True


def viz_problems(bag: Path, skip_topics: frozenset[str] = frozenset()) -> list[str]:
    """What in the Foxglove layout or the RViz config does not fit ``bag`` (the node's outputs as recorded); []
    when all fits. ``skip_topics``: topics the bag is known not to hold (their schema is then not checked here)."""
    from xmetro_ros.bag.reader import BagReader

    reader = BagReader(bag)
    topics = reader.topics()
    first: dict[str, Any] = {}
    for m in reader.messages():
        first.setdefault(m.topic, m.msg)
    problems = []
    for where, topic, schema, reads in references():
        if topic in skip_topics:
            continue
        if topic not in topics:
            problems.append(f"{where}: {topic} is not in {bag} (topics: {sorted(topics)})")
            continue
        if topics[topic] != schema:
            problems.append(f"{where}: {topic} is a {topics[topic]}, the panel needs {schema}")
            continue
        if topic not in first:
            problems.append(f"{where}: {topic} has no message in {bag}")
            continue
        if schema == CLOUD and reads and reads not in [f.name for f in first[topic].fields]:
            problems.append(f"{where}: {topic} has no PointField {reads!r} "
                            f"(fields {[f.name for f in first[topic].fields]})")
        if schema != CLOUD and reads and not _message_field(schema, reads):
            problems.append(f"{where}: {reads!r} is not a field of {schema}")
    # frames: the clouds' header.frame_id (no TF in the bag: the display frame is the clouds' own)
    frames = {first[t].header.frame_id for _, t, s, _ in references() if s == CLOUD and t in first}
    fixed = load_rviz()["Visualization Manager"]["Global Options"]["Fixed Frame"]
    if frames != {fixed}:
        problems.append(f"rviz Fixed Frame {fixed!r}, the clouds' frame_id {sorted(frames)}")
    for pid, cfg in load_layout()["configById"].items():
        if pid.startswith("3D!"):
            used = {cfg["followTf"], *(g.get("frameId") for g in cfg.get("layers", {}).values())}
            if used != frames:
                problems.append(f"{pid}: frames {sorted(used)}, the clouds' frame_id {sorted(frames)}")
        if pid.startswith("DiagnosticStatusPanel!") and cfg.get("selectedName") and "/diagnostics" in first:
            names = {s.name for m in reader.messages(topics=["/diagnostics"]) for s in m.msg.status}
            if cfg["selectedName"] not in names:
                problems.append(f"{pid}: no status named {cfg['selectedName']!r} on /diagnostics ({sorted(names)})")
    # RViz subscribes with the display's QoS: a reliable subscription needs a reliable publisher
    for d in cloud_displays():
        offered = reader.offered_qos(d["Topic"]["Value"])
        if d["Topic"]["Reliability Policy"] == "Reliable" and re.search(r"reliability: best_effort", offered):
            problems.append(f"rviz {d['Name']}: Reliable subscription, the recorded publisher offers best effort")
    return problems


def test_layout_and_rviz_config_show_what_issue_27_asks():
    lay = load_layout()
    assert {"configById", "globalVariables", "userNodes", "layout"} <= set(lay)
    panels = lay["configById"]
    # every panel of the tree is configured, and every configured panel is in the tree, each of a known type
    leaves = _layout_leaves(lay["layout"])
    assert sorted(leaves) == sorted(panels) and len(set(leaves)) == len(leaves), (leaves, sorted(panels))
    assert {p.split("!")[0] for p in panels} <= set(PANEL_SCHEMA), sorted(panels)
    clouds = {pid: cfg for pid, cfg in panels.items() if pid.startswith("3D!")}
    colour = {s["colorField"] for cfg in clouds.values() for t, s in cfg["topics"].items()
              if t == "/xmetro_node/deviations" and s.get("visible") and s.get("colorMode") == "colormap"}
    assert "dnorm" in colour and "flags" in colour and colour & {"ux", "uy", "uz"}, colour
    refs = references()
    assert any(w.startswith("RawMessages!") and t == "/xmetro_node/quality" for w, t, _, _ in refs)  # the verdict
    assert any(w.startswith("DiagnosticSummary!") and t == "/diagnostics" for w, t, _, _ in refs)
    assert any(w.startswith("Plot!") and r == "usable_fraction" for w, _, _, r in refs)
    # RViz: PointCloud2 displays coloured by intensity from the same three channels
    rv = load_rviz()
    assert {"Panels", "Visualization Manager", "Window Geometry"} <= set(rv)
    displays = cloud_displays()
    assert all(d["Color Transformer"] == "Intensity" for d in displays), displays
    channels = {d["Channel Name"] for d in displays}
    assert "dnorm" in channels and "flags" in channels and channels & {"ux", "uy", "uz"}, channels
    assert sum(bool(d["Enabled"]) for d in displays) == 1  # the same points three times: one shown at a time
    assert rv["Visualization Manager"]["Views"]["Current"]["Target Frame"] == "<Fixed Frame>"


def test_configs_fit_the_node_outputs_of_the_shipped_golden_bag():
    """The goldens are the node's outputs (`xmetro predict`): clouds and ScanQuality with their schemas, fields
    and frame. /diagnostics is only in a live node's recording (test_demo checks it there): here its schema is the
    one the recorder writes."""
    from xmetro_ros.ros.node_outputs import DIAGNOSTICS_TYPE

    problems = viz_problems(ROOT / "bags" / "golden" / "demo.mcap", skip_topics=frozenset({"/diagnostics"}))
    assert not problems, "\n".join(problems)
    assert DIAGNOSTICS_TYPE == DIAGNOSTICS


def test_configs_are_installed():
    """colcon: CMake installs config/ whole; pip: setup.py copies config/ into the package and the package data
    globs must take the two files (test_packaging checks the built wheel)."""
    import tomllib

    cmake = (ROOT / "CMakeLists.txt").read_text()
    assert "install(DIRECTORY config DESTINATION share/${PROJECT_NAME})" in cmake
    globs = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["xmetro_ros"]
    for f in (LAYOUT, RVIZ):
        rel = str(f.relative_to(ROOT))
        assert any(fnmatch.fnmatch(rel, g) and rel.count("/") == g.count("/") for g in globs), (rel, globs)
