"""The PointNet graph's per-point layers as 2-D Gemm nodes (learn/onnx_gemm.py): the same outputs to the bit as the
graph torch writes, on sets of any size, with fewer nodes; the shipped model sets are written that way."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("onnx")

from onnx_bits import assert_same_bits


@pytest.mark.parametrize(("block1", "block2", "head", "sigma"), [((32,), (64,), (32,), True),
                                                                ((16, 24), (32, 48), (40, 24), False)])
def test_rewritten_pointnet_gives_the_same_bits(block1, block2, head, sigma) -> None:
    """A PointNet (random weights; the shipped layout and a deeper one, with and without the spread head) exported
    with and without the rewrite: identical outputs on sets of 128 × 50, 3 × 1 and 1 × 7 points, every per-point
    MatMul + Add [+ Relu] gone (the global feature's MatMul, whose Add is not a bias, stays)."""
    import torch

    from xmetro_ros.learn.export import export_pointnet
    from xmetro_ros.learn.pointnet import PointNetReg

    torch.manual_seed(0)
    net = PointNetReg(14, block1=block1, block2=block2, head=head, n_out=3, sigma_head=sigma)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(torch.randn_like(p) * 0.1)  # biases not zero: their Adds matter
    plain, gemm = export_pointnet(net, 14, gemm=False), export_pointnet(net, 14)
    ops = [n.op_type for n in gemm.graph.node]
    n_layers = len(block1) + len(block2) + len(head) + 1 + int(sigma)  # trunk, blocks, head layers, output heads
    assert ops.count("Gemm") == n_layers, ops
    assert ops.count("MatMul") == [n.op_type for n in plain.graph.node].count("MatMul") - n_layers
    assert_same_bits(plain, gemm, ((128, 50, 14), (3, 1, 14), (1, 7, 14)), 1 + int(sigma))


def test_a_graph_without_per_point_layers_is_unchanged() -> None:
    """A graph whose MatMul has no bias Add (nothing to fuse) comes back as it was, 0 rewritten."""
    from onnx import TensorProto, helper, numpy_helper

    from xmetro_ros.learn.onnx_gemm import pointwise_gemm

    w = numpy_helper.from_array(np.ones((4, 2), np.float32), "W")
    g = helper.make_graph([helper.make_node("MatMul", ["X", "W"], ["y"])], "g",
                          [helper.make_tensor_value_info("X", TensorProto.FLOAT, [None, None, 4])],
                          [helper.make_tensor_value_info("y", TensorProto.FLOAT, [None, None, 2])], [w])
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    out, count = pointwise_gemm(m)
    assert count == 0 and out.SerializeToString() == m.SerializeToString()


def test_the_shipped_model_sets_are_written_with_gemm() -> None:
    """Every shipped PointNet file (default, pose, the search ensemble) runs its per-point layers as Gemm."""
    import onnx

    from xmetro_ros.scan.resources import default_model_dir

    root = default_model_dir().parent
    files = sorted(root.rglob("pointnet_multi_xyz.onnx"))
    assert len(files) >= 5
    for f in files:
        ops = [n.op_type for n in onnx.load(str(f)).graph.node]
        assert ops.count("Gemm") == 5 and ops.count("MatMul") == 1, (f, ops)
