"""int8 weights for a policy graph: a quarter of the bytes read at every decision.

A paper-sized policy holds 6.9 MB of float32 weights in three products (the LSTM's input and
recurrent matrices, the hidden layer). A daemon deciding a few times a second finds them gone
from its caches each time and reads them from memory; in int8 they are 1.7 MB. The products are
quantised the way onnxruntime's dynamic quantisation does it: weights per output column,
symmetric int8, stored in the file; each decision quantises its activations (per tensor, uint8)
and runs integer products. The weights use 7 of the 8 bits (`reduce_range`): on x86 CPUs
without VNNI, onnxruntime multiplies uint8 by int8 with an instruction (VPMADDUBSW) whose
16-bit sums of pairs saturate at full range; measured on an AVX2 machine with onnxruntime 1.32,
full-range weights moved the Q values by up to 0.026 and changed 14 % of greedy choices, 7-bit
ones by 0.008 (`tests/training/test_quantize.py`). The lidar convolutions (8 KB) and the output
layer (the Q values themselves) stay float32.

The graph as exported feeds each LSTM matrix through a Transpose, which the quantiser does not
look through, so those are first folded into initializers named `P_Transposed`
(`contracts.policy_file.TRANSPOSED_SUFFIX`); the quantiser names the hidden layer's the same way.
`controller.onnx_file.float_weights` reads such a file's parameters back by their training
names.
"""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

import onnx
from onnx import numpy_helper

from qnav.contracts.policy_file import QUANTIZED_SUFFIXES, TRANSPOSED_SUFFIX

INT8_PARAMETERS = ("lstm.weight_ih_l0", "lstm.weight_hh_l0", "head.0.weight")
"""The training parameters stored in int8: every large product but the output layer."""


def fold_weight_transposes(model: onnx.ModelProto) -> None:
    """Replace each Transpose of an initializer by an initializer `NAME_Transposed` holding the
    transposed array (in place); its consumers read the new initializer."""
    initializers = {tensor.name: tensor for tensor in model.graph.initializer}
    renamed: dict[str, str] = {}
    kept = []
    for node in model.graph.node:
        if node.op_type != "Transpose" or node.input[0] not in initializers:
            kept.append(node)
            continue
        array = numpy_helper.to_array(initializers[node.input[0]])
        perm = [list(a.ints) for a in node.attribute if a.name == "perm"]
        folded = array.transpose(perm[0]) if perm else array.T
        name = node.input[0] + TRANSPOSED_SUFFIX
        model.graph.initializer.append(numpy_helper.from_array(folded.copy(), name))
        renamed[node.output[0]] = name
    for node in kept:
        for i, name in enumerate(node.input):
            node.input[i] = renamed.get(name, name)
    del model.graph.node[:]
    model.graph.node.extend(kept)
    used = {name for node in kept for name in node.input}
    unused = [tensor for tensor in model.graph.initializer if tensor.name not in used]
    for tensor in unused:
        model.graph.initializer.remove(tensor)


def quantize_int8(model: onnx.ModelProto) -> onnx.ModelProto:
    """`model` with the products over `INT8_PARAMETERS` in int8 (onnxruntime's dynamic
    quantisation, weights per column); metadata is not carried over."""
    from onnxruntime.quantization import QuantType, quantize_dynamic

    folded = onnx.ModelProto()
    folded.CopyFrom(model)
    fold_weight_transposes(folded)
    names = {tensor.name for tensor in folded.graph.initializer}
    present = [p for p in INT8_PARAMETERS if p in names or p + TRANSPOSED_SUFFIX in names]
    weights = {p + suffix for p in present for suffix in ("", TRANSPOSED_SUFFIX)}
    # The quantiser first rewrites each Gemm as a MatMul named NAME_MatMul (and an Add).
    excluded = [
        name
        for node in folded.graph.node
        if node.op_type in ("MatMul", "Gemm") and not weights & set(node.input)
        for name in (node.name, node.name + "_MatMul")
    ]
    with tempfile.TemporaryDirectory() as scratch:
        source, target = Path(scratch) / "float32.onnx", Path(scratch) / "int8.onnx"
        onnx.save_model(folded, source)
        # It advises pre-processing (shape inference) on the root logger: the graph has shapes.
        root = logging.getLogger()
        level = root.level
        root.setLevel(logging.ERROR)
        try:
            quantize_dynamic(
                source,
                target,
                op_types_to_quantize=["MatMul", "Gemm"],
                nodes_to_exclude=excluded,
                per_channel=True,
                reduce_range=True,
                weight_type=QuantType.QInt8,
            )
        finally:
            root.setLevel(level)
        quantized = onnx.load_model(target)
    suffix = QUANTIZED_SUFFIXES[0]
    stored = {
        t.name.removesuffix(suffix) for t in quantized.graph.initializer if t.name.endswith(suffix)
    }
    wanted = {p + TRANSPOSED_SUFFIX for p in present}
    if stored != wanted:
        raise ValueError(
            f"the quantiser stored {sorted(stored)} in int8 where {sorted(wanted)} were meant"
        )
    return quantized
