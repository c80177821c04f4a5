"""A PointNet graph's element-wise steps with a per-channel constant run on rows of a whole set, not of one point.

``torch.onnx.export`` writes the network's input standardisation and output scaling — (X − mean) / std on the
features (sets, points, 14), y × scale and log σ̂ + log(scale) on the outputs (sets, points, 3) — as element-wise
nodes that broadcast a (C,) constant over every point. ONNX Runtime runs such a broadcast one span of C values at a
time: 14 or 3 values per call, so these four nodes took a quarter of a run (its profile of a chunk of 128 sets of the
shipped PointNet at 1 thread: Sub 0.19 ms, Div 0.19, Mul 0.17, Add 0.17 of 2.8 ms; the Gemms ~1.3).
:func:`wide_broadcasts` rewrites each such node Op(a, c), ``a`` (sets, points, C) and ``c`` a (C,) constant, into
Op(Reshape(a, (sets, points·C)), Tile(c, points)) and reshapes back where a node other than such a step, or a graph
output, reads it: the same scalar operation on the same pair of values for every element, spans of points·C values
per call. The outputs are the same bits (element-wise IEEE arithmetic does not depend on the layout; checked for
the shipped models by ``tools/gemm_models.py`` and for fresh exports by ``test/test_onnx_broadcast.py``); a chunk of
128 sets: 1.91 → 1.39 ms side by side on this host.

Why not fold the constants into the first and last layers' weights (fewer nodes still): that changes every output by
float32 rounding, and the published predictions would no longer be the ones the card's figures were measured with.
Why here and not at load: the runtime path does not depend on the ``onnx`` package; the rewrite runs at export and
once on the shipped files, as :mod:`.onnx_gemm`'s does.
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import onnx
from onnx import helper, numpy_helper, shape_inference

__all__ = ["wide_broadcasts"]

_BINARY = {"Sub", "Div", "Mul", "Add"}
# unary steps of a constant that stay a constant (log σ̂'s Add reads Log(scale))
_CONSTANT_UNARY = {"Log", "Exp", "Neg", "Reciprocal", "Sqrt", "Abs"}
_PREFIX = "xmetro_wide"


def _dims(vi: onnx.ValueInfoProto) -> list[str | int]:
    return [d.dim_param or d.dim_value for d in vi.type.tensor_type.shape.dim]


def wide_broadcasts(model: onnx.ModelProto) -> tuple[onnx.ModelProto, int]:
    """(a copy of ``model`` whose per-point element-wise Sub / Div / Mul / Add with a (C,) constant run on
    (sets, points·C) rows, how many nodes were rewritten). Per point means: the tensor's shape is the graph input's
    named (sets, points) and then C, by ONNX shape inference. A graph with none comes back unchanged (0)."""
    m = onnx.ModelProto()
    m.CopyFrom(model)
    g = m.graph
    inferred = shape_inference.infer_shapes(m)
    shapes = {vi.name: _dims(vi) for vi in (*inferred.graph.value_info, *inferred.graph.input,
                                            *inferred.graph.output)}
    x = g.input[0].name
    lead = shapes[x][:2]
    if len(lead) != 2 or not all(isinstance(d, str) and d for d in lead):
        return m, 0  # without named (sets, points) dims, "per point" cannot be told from the shapes
    const: dict[str, list[int]] = {i.name: list(i.dims) for i in g.initializer}
    nodes = list(g.node)
    for n in nodes:
        if n.op_type in _CONSTANT_UNARY and len(n.input) == 1 and n.input[0] in const:
            const[n.output[0]] = const[n.input[0]]

    def step(n: onnx.NodeProto) -> tuple[str, str, bool] | None:
        """(the per-point input, the (C,) constant, whether the constant is the first operand) or None."""
        if n.op_type not in _BINARY or len(n.input) != 2:
            return None
        first, second = (i in const for i in n.input)
        if first == second:
            return None
        a, c = (n.input[1], n.input[0]) if first else (n.input[0], n.input[1])
        for name in (a, n.output[0]):  # a reshape's output may have lost its dims in the inference; the result not
            s = shapes.get(name)
            if s and len(s) == 3 and s[:2] == lead and isinstance(s[2], int) and const[c] == [s[2]]:
                return a, c, first
        return None

    steps = [step(n) for n in nodes]
    if not any(steps):
        return m, 0
    consumers: dict[str, list[int]] = defaultdict(list)
    for k, n in enumerate(nodes):
        for i in n.input:
            consumers[i].append(k)
    outputs = {o.name for o in g.output}
    new: list[onnx.NodeProto] = []

    def int64(name: str, values: list[int]) -> str:
        value = numpy_helper.from_array(np.asarray(values, np.int64))
        new.append(helper.make_node("Constant", [], [name], value=value))
        return name

    # the number of points, from the input's shape (every per-point tensor has it), and (sets, −1): Reshape's 0
    # copies the input's dim
    shape, points = f"{_PREFIX}_shape", f"{_PREFIX}_points"
    new.append(helper.make_node("Shape", [x], [shape]))
    new.append(helper.make_node("Slice", [shape, int64(f"{_PREFIX}_1", [1]), int64(f"{_PREFIX}_2", [2])], [points]))
    rows = int64(f"{_PREFIX}_rows", [0, -1])
    wide: dict[str, str] = {}
    tiled: dict[str, str] = {}
    back: dict[int, str] = {}
    count = 0
    for k, n in enumerate(nodes):
        found = steps[k]
        if found is None:
            new.append(n)
            continue
        a, c, const_first = found
        if a not in wide:
            wide[a] = f"{a}_{_PREFIX}"
            new.append(helper.make_node("Reshape", [a, rows], [wide[a]]))
        if c not in tiled:
            tiled[c] = f"{c}_{_PREFIX}"
            new.append(helper.make_node("Tile", [c, points], [tiled[c]]))
        out = n.output[0]
        wide[out] = f"{out}_{_PREFIX}"
        operands = [tiled[c], wide[a]] if const_first else [wide[a], tiled[c]]
        new.append(helper.make_node(n.op_type, operands, [wide[out]]))
        count += 1
        if out in outputs or any(steps[j] is None for j in consumers[out]):
            width = const[c][0]
            if width not in back:
                back[width] = int64(f"{_PREFIX}_points_by_{width}", [0, -1, width])
            new.append(helper.make_node("Reshape", [wide[out], back[width]], [out]))
    del g.node[:]
    g.node.extend(new)
    onnx.checker.check_model(m)
    return m, count
