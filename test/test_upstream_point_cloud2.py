"""sensor_msgs_py's own test file (ros2/common_interfaces, sensor_msgs_py/test/test_point_cloud2.py) run against
xmetro_ros.ros.cloud: 18/18 expected.

The upstream file is not copied into this repository (this workplace's rule: code fetched from public repositories
stays out of our commits). Point ``XMETRO_UPSTREAM_PC2_TEST`` at a copy of the file as upstream has it at commit
c0c0bc57f958eb54a142446f0c2a475754367eee (rolling; the file last changed in bf7dbe8e, "Allow pointcloud
create_cloud function to set specific point_step (#223)"); its SHA-256 is checked, its one import line is pointed
at our module in memory, and the 18 tests must pass. Without the variable the test is skipped (and says so).
"""

from __future__ import annotations

import hashlib
import os
import sys
import types
import unittest
from pathlib import Path

import pytest

UPSTREAM_SHA256 = "094f17b85490580c33870e9312c0bad165058816d730d9d4a810a2970aa8bc72"
IMPORT_LINE = "from sensor_msgs_py import point_cloud2\n"


def test_upstream_sensor_msgs_py_tests_pass_on_cloud_py():
    path = os.environ.get("XMETRO_UPSTREAM_PC2_TEST")
    if not path:
        pytest.skip("XMETRO_UPSTREAM_PC2_TEST not set (path to upstream's test_point_cloud2.py)")
    text = Path(path).read_text()
    assert hashlib.sha256(text.encode()).hexdigest() == UPSTREAM_SHA256, "not the pinned upstream file"
    assert text.count(IMPORT_LINE) == 1
    text = text.replace(IMPORT_LINE, "import xmetro_ros.ros.cloud as point_cloud2\n")
    mod = types.ModuleType("upstream_test_point_cloud2")
    sys.modules[mod.__name__] = mod
    try:
        exec(compile(text, path, "exec"), mod.__dict__)
        suite = unittest.defaultTestLoader.loadTestsFromModule(mod)
        result = unittest.TextTestRunner(verbosity=0, stream=open(os.devnull, "w")).run(suite)
    finally:
        del sys.modules[mod.__name__]
    problems = [f"{t.id()}: {tb.splitlines()[-1]}" for t, tb in result.failures + result.errors]
    assert result.testsRun == 18 and not problems, problems
