"""The package's import graph (test/import_graph.py): no import circle anywhere, every package imports only what
its docstring's ``May import:`` line allows, a handful of modules beside the packages, and docs/architecture.md's
layer diagram is the one the docstrings give. Each check is shown to fail on a synthetic tree that breaks it."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from import_graph import ImportGraph

ROOT = Path(__file__).resolve().parents[1]
MAX_ENTRY_MODULES = 2  # beside __init__.py: at most 3 modules at the top of xmetro_ros/


@pytest.fixture(scope="module")
def graph() -> ImportGraph:
    return ImportGraph.scan(ROOT)


def test_no_import_circle(graph):
    assert len(graph.modules) > 100 and len(graph.edges) > 500  # the real tree was read
    assert graph.cycles() == []


def test_every_package_declares_what_it_may_import_and_the_declarations_form_layers(graph):
    assert graph.declaration_errors() == []
    assert {"scan", "judge", "parts", "calibrate", "plan", "monitor", "sim", "preprocess", "learn", "loop", "bag",
            "ros", "apps", "compute"} <= set(graph.packages())
    layers = graph.layers()
    # the thread budget under everything that runs a parallel kernel; the scan vocabulary right above it
    assert layers[0] == ["bag", "compute"] and layers[1] == ["scan"] and layers[-1] == ["apps"]


def test_packages_import_only_what_they_declare(graph):
    assert graph.layer_violations() == []


def test_the_node_layer_never_declares_training_or_tools(graph):
    """The node does not load the training stack or the command-line tools (runtime check: test_inference.py)."""
    assert not graph.allowed()["ros"] & {"learn", "loop", "calibrate", "apps"}
    assert not graph.allowed()["judge"] & {"learn", "loop", "calibrate", "apps", "ros"}


def test_few_modules_beside_the_packages(graph):
    entries = graph.entry_modules()
    assert len(entries) <= MAX_ENTRY_MODULES, entries
    for m in entries:  # entry-level modules only forward to a package (a documented `python -m` path)
        assert len(graph.modules[m].read_text().splitlines()) < 15, m


def test_architecture_doc_shows_the_generated_diagram(graph):
    doc = (ROOT / "docs" / "architecture.md").read_text()
    assert f"```\n{graph.diagram()}\n```" in doc, "regenerate with: python test/import_graph.py"


# -- the checks fail where they should: a synthetic tree --------------------------------------------------------

def _tree(tmp_path: Path, files: dict[str, str]) -> ImportGraph:
    for rel, text in files.items():
        p = tmp_path / "xmetro_ros" / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return ImportGraph.scan(tmp_path)


BASE = {
    "__init__.py": '"""Root."""\n',
    "low/__init__.py": '"""Low.\n\nMay import: nothing of xmetro_ros.\n"""\n',
    "low/a.py": "X = 1\n",
    "low/b.py": "from .a import X\n",
    "high/__init__.py": '"""High.\n\nMay import: low.\n"""\n',
    "high/c.py": "from ..low.b import X\n",
}


def test_a_clean_synthetic_tree_passes(tmp_path):
    g = _tree(tmp_path, BASE)
    assert g.cycles() == [] and g.layer_violations() == [] and g.declaration_errors() == []
    assert g.layers() == [["low"], ["high"]]


def test_a_circle_is_found_even_through_a_function_level_import(tmp_path):
    g = _tree(tmp_path, {**BASE, "low/a.py": "X = 1\n\n\ndef f():\n    from .b import X\n    return X\n"})
    assert g.cycles() == [["xmetro_ros.low.a", "xmetro_ros.low.b", "xmetro_ros.low.a"]]


def test_a_type_only_circle_across_three_modules_is_found(tmp_path):
    g = _tree(tmp_path, {**BASE,
                         "high/d.py": "from .e import E\n",
                         "high/e.py": ("from typing import TYPE_CHECKING\n"
                                       "if TYPE_CHECKING:\n    from .f import F\nE = 1\n"),
                         "high/f.py": "from .d import *\nF = 1\n"})
    (circle,) = g.cycles()
    assert set(circle) == {"xmetro_ros.high.d", "xmetro_ros.high.e", "xmetro_ros.high.f"} and len(circle) == 4


def test_a_package_importing_its_own_init_that_imports_it_is_a_circle(tmp_path):
    g = _tree(tmp_path, {**BASE, "low/__init__.py": '"""Low.\n\nMay import: nothing.\n"""\nfrom .b import X\n',
                         "low/a.py": "from . import X\n"})
    assert g.cycles() != []


def test_from_package_import_submodule_is_an_edge_to_the_submodule_not_the_package(tmp_path):
    g = _tree(tmp_path, {**BASE, "low/__init__.py": '"""Low.\n\nMay import: nothing.\n"""\nfrom .a import f\n',
                         "low/a.py": "def f():\n    from . import b\n    return b\n", "low/b.py": "X = 2\n"})
    assert g.cycles() == []  # a -> low/__init__ -> a would be a circle if `from . import b` meant the package
    assert [e.dst for e in g.edges if e.src == "xmetro_ros.low.a"] == ["xmetro_ros.low.b"]


def test_an_upward_import_is_a_layer_violation(tmp_path):
    g = _tree(tmp_path, {**BASE, "low/a.py": "def f():\n    from ..high import c\n    return c\n"})
    (v,) = g.layer_violations()
    assert v.startswith("low/a.py:2 imports xmetro_ros.high.c") and "low may import nothing" in v


def test_an_undeclared_sideways_import_is_a_layer_violation(tmp_path):
    g = _tree(tmp_path, {**BASE, "side/__init__.py": '"""Side.\n\nMay import: low.\n"""\n',
                         "side/s.py": "import xmetro_ros.high.c as c\n"})
    assert [v.split(" (")[0] for v in g.layer_violations()] == ["side/s.py:1 imports xmetro_ros.high.c"]


def test_importing_an_entry_module_is_a_violation(tmp_path):
    g = _tree(tmp_path, {**BASE, "tool.py": "from .high.c import X\n", "high/c.py": "from ..tool import X\n"})
    assert any("an entry module" in v for v in g.layer_violations())


def test_missing_unknown_or_circular_declarations_are_reported(tmp_path):
    g = _tree(tmp_path, {**BASE, "high/__init__.py": '"""High, no declaration."""\n'})
    assert g.declaration_errors() == ["high: no 'May import:' line in its __init__.py docstring"]
    g = _tree(tmp_path, {**BASE, "high/__init__.py": '"""High.\n\nMay import: low, nowhere.\n"""\n'})
    assert g.declaration_errors() == ["high: may import unknown package 'nowhere'"]
    g = _tree(tmp_path, {**BASE, "low/__init__.py": '"""Low.\n\nMay import: high.\n"""\n'})
    assert any("circle" in e for e in g.declaration_errors())
