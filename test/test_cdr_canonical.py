"""Canonical CDR: the alignment padding of a message's serialisation zeroed, every value unchanged."""

from __future__ import annotations

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

from xmetro_ros.msg import ScanQuality
from xmetro_ros.ros.cdr_canonical import CdrLayoutError, canonical_cdr, padding_spans
from xmetro_ros.ros.cloud import create_cloud_from_arrays
from xmetro_ros.ros.node_outputs import cloud_arrays, quality_dict


def _cloud(frame: str) -> PointCloud2:
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(500, 3)).astype(np.float32)
    return create_cloud_from_arrays(Header(frame_id=frame), {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2],
                                                             "flags": np.arange(500, dtype=np.uint16)})


def _quality() -> ScanQuality:
    q = ScanQuality()
    q.header.frame_id = "artifact"
    q.model_id = "m-1"
    q.verdict = 1
    q.flag_names = ["outlier", "grazing"]
    q.flag_counts = [3, 4]
    q.mean_abs_error = [1e-5, 2e-5, 3e-5]
    q.p95_abs_error = [4e-5, 5e-5, 6e-5]
    q.usable_fraction = 0.9
    q.settings.scanner_id = "xm-ls90"
    q.settings.exposure_time = 0.001
    return q


@pytest.mark.parametrize("frame", ["a", "artifact", "abcd", "abc"])
def test_padding_zeroed_values_unchanged(frame):
    for msg in (_cloud(frame), _quality()):
        raw = serialize_message(msg)
        spans = padding_spans(msg, len(raw))
        c = canonical_cdr(msg)
        assert len(c) == len(raw) and c == canonical_cdr(msg)
        mask = np.ones(len(raw), bool)
        for a, b in spans:
            mask[a:b] = False
            assert c[a:b] == bytes(b - a)
        # only padding may change: every other byte is the serialiser's
        assert np.array_equal(np.frombuffer(raw, np.uint8)[mask], np.frombuffer(c, np.uint8)[mask])
        back = deserialize_message(c, type(msg))
        if isinstance(msg, PointCloud2):
            a, b = cloud_arrays(back), cloud_arrays(msg)
            assert all(np.array_equal(a[k], b[k]) for k in b) and back.header.frame_id == frame
        else:
            assert quality_dict(back) == quality_dict(msg)
    # "artifact" + NUL = 9 bytes after a 4-byte length: 3 bytes of padding before the uint32 height
    if frame == "artifact":
        assert any(b - a == 3 for a, b in padding_spans(_cloud(frame)))


def test_layout_mismatch_is_an_error():
    msg = _quality()
    with pytest.raises(CdrLayoutError):
        padding_spans(msg, len(serialize_message(msg)) + 4)
