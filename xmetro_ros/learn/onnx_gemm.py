"""A PointNet graph's per-point layers as 2-D Gemm nodes, which ONNX Runtime fuses with their bias and ReLU.

``torch.onnx.export`` writes a ``Linear`` on sets (K, n, F) as MatMul of the 3-D tensor by a weight, then a separate
Add of the bias (and a separate Relu): ONNX Runtime's fusions (Gemm + bias + activation) need a 2-D Gemm, so each of
those ran as its own pass over the (K·n, width) activations. On the shipped PointNet at 1 thread the bias Adds took
as long as the MatMuls (ONNX Runtime's profile of a chunk of 128 sets: MatMuls 0.55 ms, Adds and Relus 0.75 ms of
1.73 ms). :func:`pointwise_gemm` rewrites each MatMul(x, W) → Add(b) [→ Relu] whose weight W (2-D) and bias b (1-D)
are initializers into Reshape(x, (−1, F)) → Gemm(x, W, b) [→ Relu], and reshapes back to (K, n, width) only where a
node other than such a layer (the max pool, the broadcast Add of the global feature) or a graph output reads it.
Gemm computes x·W then adds b, as MatMul then Add did: the outputs are the same bits (checked for the shipped models
by ``tools/gemm_models.py`` and for a fresh export by ``test/test_onnx_gemm.py``). One chunk: 1.73 → ~1.3 ms.

Why here and not by ONNX Runtime: its MatMul + Add fusion takes 2-D inputs only, and the runtime path does not
depend on the ``onnx`` package (the rewrite runs at export, and once on the shipped model files).
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import onnx
from onnx import helper, numpy_helper

__all__ = ["pointwise_gemm"]


def pointwise_gemm(model: onnx.ModelProto) -> tuple[onnx.ModelProto, int]:
    """(a copy of ``model`` with its per-point MatMul + Add [+ Relu] layers as 2-D Gemm nodes, how many were
    rewritten); any leading dims (sets, points) are flattened and restored. A graph with none of these layers comes
    back unchanged (0)."""
    m = onnx.ModelProto()
    m.CopyFrom(model)
    g = m.graph
    inits = {i.name: i for i in g.initializer}
    consumers: dict[str, list[onnx.NodeProto]] = defaultdict(list)
    for n in g.node:
        for i in n.input:
            consumers[i].append(n)
    outputs = {o.name for o in g.output}

    def layer(n: onnx.NodeProto) -> tuple[onnx.NodeProto, onnx.NodeProto | None] | None:
        """(the Add, the Relu or None) of a MatMul that is a per-point layer, else None."""
        if n.op_type != "MatMul" or n.input[1] not in inits or len(inits[n.input[1]].dims) != 2:
            return None
        cons = consumers[n.output[0]]
        if len(cons) != 1 or cons[0].op_type != "Add" or n.output[0] in outputs:
            return None
        add = cons[0]
        bias = [i for i in add.input if i != n.output[0]]
        if len(bias) != 1 or bias[0] not in inits or len(inits[bias[0]].dims) != 1:
            return None
        if inits[bias[0]].dims[0] != inits[n.input[1]].dims[1]:
            return None
        relu = consumers[add.output[0]]
        if len(relu) == 1 and relu[0].op_type == "Relu" and add.output[0] not in outputs:
            return add, relu[0]
        return add, None

    layers = {id(n): layer(n) for n in g.node}
    if not any(layers.values()):
        return m, 0
    new_nodes: list[onnx.NodeProto] = []
    skip: set[int] = set()
    flat: dict[str, tuple[str, str]] = {}  # 3-D tensor → (its 2-D alias, the tensor holding its leading dims)
    targets: dict[tuple[str, int], str] = {}  # (leading dims, width) → the 3-D shape to reshape back to
    count = 0

    def name(stem: str) -> str:
        return f"xmetro_gemm_{stem}_{len(new_nodes)}"

    def const(values: list[int]) -> str:
        # a Constant node, not an initializer: the initializers stay the network's parameters (learn/prior.py
        # reads them back as its state)
        out = name("c")
        new_nodes.append(helper.make_node("Constant", [], [out],
                                          value=numpy_helper.from_array(np.asarray(values, np.int64))))
        return out

    def as_2d(x: str, width: int) -> tuple[str, str]:
        if x in flat:
            return flat[x]
        shape, lead, x2 = name("shape"), name("lead"), name("flat")
        new_nodes.extend([helper.make_node("Shape", [x], [shape]),
                          helper.make_node("Slice", [shape, const([0]), const([-1])], [lead]),
                          helper.make_node("Reshape", [x, const([-1, width])], [x2])])
        flat[x] = (x2, lead)
        return flat[x]

    def target(lead: str, width: int) -> str:
        if (lead, width) not in targets:
            t = name("target")
            new_nodes.append(helper.make_node("Concat", [lead, const([width])], [t], axis=0))
            targets[(lead, width)] = t
        return targets[(lead, width)]

    for n in g.node:
        if id(n) in skip:
            continue
        found = layers[id(n)]
        if found is None:
            new_nodes.append(n)
            continue
        add, relu = found
        k, width = (int(d) for d in inits[n.input[1]].dims)
        x2, lead = as_2d(n.input[0], k)
        bias = next(i for i in add.input if i != n.output[0])
        # the Gemm writes the MatMul's output name, which it replaces (the layer's provenance, /block1/block1.0/...,
        # is what learn/prior.py reads the weights back by)
        y2 = n.output[0]
        new_nodes.append(helper.make_node("Gemm", [x2, n.input[1], bias], [y2]))
        out = add.output[0]
        skip.add(id(add))
        if relu is not None:
            r2 = f"{relu.output[0]}_rows"
            new_nodes.append(helper.make_node("Relu", [y2], [r2]))
            y2, out = r2, relu.output[0]
            skip.add(id(relu))
        count += 1
        flat[out] = (y2, lead)
        # back to (sets, points, width) only for readers that are not per-point layers themselves
        if out in outputs or any(layers.get(id(c)) is None for c in consumers[out]):
            new_nodes.append(helper.make_node("Reshape", [y2, target(lead, width)], [out]))
    del g.node[:]
    g.node.extend(new_nodes)
    onnx.checker.check_model(m)
    return m, count
