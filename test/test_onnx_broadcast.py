"""The PointNet graph's input standardisation and output scaling on whole sets' rows (learn/onnx_broadcast.py): the
same outputs to the bit as the graph torch writes, on sets of any size; the shipped model sets are written that way."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("onnx")

from onnx_bits import assert_same_bits


def _net(sigma: bool):
    import torch

    from xmetro_ros.learn.pointnet import PointNetReg

    torch.manual_seed(0)
    net = PointNetReg(14, block1=(32,), block2=(64,), head=(32,), n_out=3, sigma_head=sigma)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(torch.randn_like(p) * 0.1)
        # a standardisation and scale that round (not 0 and 1): each element-wise step changes the bits
        net.x_mean.copy_(torch.randn(14) * 3.0)
        net.x_std.copy_(torch.rand(14) * 2.0 + 0.3)
        net.y_scale.copy_(torch.rand(3) * 0.05 + 0.01)
    return net


@pytest.mark.parametrize("gemm", [True, False])
@pytest.mark.parametrize("sigma", [True, False])
def test_wide_broadcasts_give_the_same_bits(gemm: bool, sigma: bool) -> None:
    """A PointNet exported with and without the rewrite (after the Gemm rewrite or on torch's own graph): identical
    outputs on sets of 128 × 50, 3 × 1, 1 × 7 and 200 × 50 points; nothing left to rewrite."""
    from xmetro_ros.learn.export import export_pointnet
    from xmetro_ros.learn.onnx_broadcast import wide_broadcasts

    net = _net(sigma)
    plain = export_pointnet(net, 14, gemm=gemm, wide=False)
    wide = export_pointnet(net, 14, gemm=gemm)
    _, count = wide_broadcasts(plain)
    # Sub, Div, Mul, and log σ̂'s Add; on torch's own graph also every per-point layer's bias Add
    assert count == 3 + int(sigma) if gemm else count > 3 + int(sigma)
    assert wide_broadcasts(wide)[1] == 0  # already written that way
    assert_same_bits(plain, wide, ((128, 50, 14), (3, 1, 14), (1, 7, 14), (200, 50, 14)), 1 + int(sigma))


def test_a_graph_without_per_point_broadcasts_is_unchanged() -> None:
    """An Add of two per-point tensors, and a Mul by a constant that is not (C,): nothing to rewrite, 0."""
    from onnx import TensorProto, helper, numpy_helper

    from xmetro_ros.learn.onnx_broadcast import wide_broadcasts

    s = numpy_helper.from_array(np.full((1,), 2.0, np.float32), "s")
    g = helper.make_graph([helper.make_node("Add", ["X", "X"], ["t"]), helper.make_node("Mul", ["t", "s"], ["y"])],
                          "g", [helper.make_tensor_value_info("X", TensorProto.FLOAT, ["sets", "points", 4])],
                          [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["sets", "points", 4])], [s])
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    out, count = wide_broadcasts(m)
    assert count == 0 and out.SerializeToString() == m.SerializeToString()


def test_the_shipped_model_sets_run_their_broadcasts_on_rows() -> None:
    """Every shipped PointNet file (default, pose, the search ensemble) has nothing left to rewrite, and its
    standardisation reads tiled constants."""
    import onnx

    from xmetro_ros.learn.onnx_broadcast import wide_broadcasts
    from xmetro_ros.scan.resources import default_model_dir

    root = default_model_dir().parent
    files = sorted(root.rglob("pointnet_multi_xyz.onnx"))
    assert len(files) >= 5
    for f in files:
        model = onnx.load(str(f))
        assert wide_broadcasts(model)[1] == 0, f
        assert [n.op_type for n in model.graph.node].count("Tile") == 4, f
