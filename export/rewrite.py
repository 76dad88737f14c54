"""ONNX graph rewrites for ONNX Runtime's CPU kernels and for INT8 (imports only onnx and numpy).

1. Transposed convolutions as ordinary ones. A stride-1 transposed conv is a
   convolution with the kernel flipped and the channel axes swapped: same
   multiply-adds, but ONNX Runtime runs ``Conv`` in its blocked NCHWc kernels and
   ``ConvTranspose`` through a slower generic path (measured here: the edge depth
   net's last 3×3 transposed conv took 3.1 ms of 22, and the whole net 4 % less
   as a conv). Each 3×3 stride-2 one (padding 1, output padding 1) becomes its
   *sub-pixel* form: output pixel (2i + a, 2j + b) only sees inputs (i, j),
   (i, j + 1), (i + 1, j) and (i + 1, j + 1), so one 2×2 convolution with one
   extra row and column of zero padding at the bottom and right computes the
   four phases a, b ∈ {0, 1} as 4·C_out channels, and ``DepthToSpace`` (CRD
   order) interleaves them. In fp32 the sub-pixel form was not faster here (its
   2×2 kernels do 16/9 the multiply-adds, 7 of 16 taps being zeros), so only the
   INT8 conversion uses it: ONNX Runtime has no quantized ``ConvTranspose``
   kernel, and the edge depth net's five transposed convs took 44 % of its INT8
   time. Both forms are exact (a test compares ONNX Runtime outputs).
2. A convolution reading a graph input whose channel count is not a multiple of
   the NCHWc block (16 floats of AVX-512) and not below it stays in ONNX
   Runtime's plain NCHW kernel: PIXOR's first conv on the 19-channel BEV took a
   quarter of the edge PIXOR's time. :func:`split_input_convs` slices the input
   into its first 16·k channels and the rest, convolves each (both get blocked
   kernels) and adds them: exact up to float summation order.
3. A convolution with fewer output channels than the block, read only by
   convolutions (directly or through a ReLU), makes ONNX Runtime reorder its
   output back to NCHW and run the next conv on its first-layer kernel: edge
   PIXOR's 12-wide first stage did that at full resolution.
   :func:`pad_narrow_convs` gives it zero output channels up to 16 and its
   readers zero input weights for them: exact.
4. The ends of the network stay in fp32 under INT8. uint8 steps over the depth
   net's 0–85 m output are 0.33 m, and its sparse-depth input has the same
   range; PIXOR's score and box heads decide what is a car (its BEV input, 0/1
   occupancy and a reflectance in [0, 1], quantizes well). :func:`boundary_nodes`
   names the nodes from each graph input to its first convolution and from the
   last convolution before each output to that output, for ``nodes_to_exclude``.

5. ``Where`` as arithmetic. ONNX Runtime's CPU ``Where`` runs element by
   element; the edge depth net's prefill has six of them on full-resolution maps
   (0.53 ms each with its Greater, against 0.07 ms as a·float(c) + b·float(¬c)).
   :func:`where_as_arithmetic` rewrites those whose two branches are provably
   finite: exact (x·1 = x, x·0 = ±0). Finite in FP32, that is: the prefill's
   1/clip(x, 1e-6) is 1e6 where the map is empty, ±∞ in FP16, and ∞·0 is NaN;
   the FP16 conversion keeps such nodes in FP32 (export/fp16.py).
6. Parallel convolutions merged. The depth net's early fusion concatenates
   ``Relu(Conv(depth))`` and ``Relu(Conv(image))``: ONNX Runtime reordered both
   outputs from its blocked layout to NCHW for the Concat and back for the next
   conv, and with an NCHW identity the first stage's residual Adds ran in NCHW
   as well. :func:`merge_parallel_convs` makes it one conv on the concatenated
   inputs with block-diagonal weights (exact zeros across).

7. Input convs whole and padded, for INT8. The split of 2. helps the fp32
   kernels but not the quantized ones: measured here (400 × 352, 16 output
   channels, uint8), a 3-channel conv took 2.8 ms, more than the 16-channel one
   (2.5 ms), and a whole 19-channel one 7.2 ms, against 3.3 ms with 20 channels
   (VNNI multiplies groups of four uint8 values). The INT8 conversion undoes the
   split (:func:`merge_split_input_convs`) and pads the input with a zero
   channel (:func:`pad_input_convs`); after quantization the Pad moves behind
   the input's QuantizeLinear and pads the uint8 tensor with its zero point
   (:func:`quantize_before_pad`). Exact: the padded channel has zero weights,
   and q(0) is the zero point.

8. Graph inputs in channel pieces. The slices of 2. are copies: ONNX Runtime ran
   them as one Split of the whole 37-channel edge BEV (1.4–1.6 ms of PIXOR's 43).
   Channels lo…hi of a C-contiguous (1, C, H, W) tensor are a contiguous block,
   so :func:`inputs_from_channel_slices` makes each slice a graph input of its
   own, named ``bev[lo:hi]``: the runtime feeds views of its one BEV buffer
   (:func:`pipeline.graph_inputs.session_feeds`) and nothing is copied.
9. Output heads merged. PIXOR's score and box heads are two 3×3 convs on the
   same features (1 and 6 output channels, each padded to a block by the
   blocked kernel): :func:`merge_output_heads` makes them one conv with the
   outputs side by side and a Split on the small result (0.9 ms of 1.8 saved
   on the edge PIXOR here).

:func:`lower_for_cpu` applies the fp32 rewrites (the stride-1 half of 1, 2, 3,
5, 6, 8 and 9); the exporter runs it on every network before the parity check, and
``python -m export.lower`` applies it to an existing model directory.
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import onnx
from onnx import helper, numpy_helper

from pipeline.graph_inputs import channel_piece, piece_name, tiles

# Kernel row (or column) of a 3×3 stride-2 transposed conv that output phase a ∈ {0, 1} takes from
# input offset d ∈ {0, 1} (input i + d for output 2i + a); None: no tap. From 2i + a = 2(i + d) − 1 + k.
_TAP = {(0, 0): 1, (0, 1): None, (1, 0): 2, (1, 1): 0}


def subpixel_weights(weight: np.ndarray, bias: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(C_in, C_out, 3, 3) transposed-conv weights → (4·C_out, C_in, 2, 2) conv weights and (4·C_out,) bias.

    Channel o·4 + a·2 + b holds phase (a, b) of output channel o: the order DepthToSpace (CRD) reads.
    """
    c_in, c_out = weight.shape[:2]
    out = np.zeros((c_out, 2, 2, c_in, 2, 2), dtype=weight.dtype)  # (o, a, b, c, dm, dn)
    for (a, dm), kh in _TAP.items():
        for (b, dn), kw in _TAP.items():
            if kh is not None and kw is not None:
                out[:, a, b, :, dm, dn] = weight[:, :, kh, kw].T
    return out.reshape(c_out * 4, c_in, 2, 2), np.repeat(bias, 4)


def _attributes(node: onnx.NodeProto) -> dict:
    return {a.name: helper.get_attribute_value(a) for a in node.attribute}


def rewrite_transposed_convs(model: onnx.ModelProto, subpixel: bool = True) -> tuple[onnx.ModelProto, int]:
    """A copy of ``model`` with its 3×3 stride-1 ConvTranspose nodes as Conv, and with ``subpixel``
    its 3×3 stride-2 ones as Conv + DepthToSpace.

    Returns the new model and the number of nodes rewritten. Transposed convs with other
    settings, or whose weights are not stored in the graph, are left as they are.
    """
    model = onnx.ModelProto.FromString(model.SerializeToString())
    graph = model.graph
    initializers = {init.name: init for init in graph.initializer}
    nodes, rewritten = [], 0
    for node in graph.node:
        attrs = _attributes(node)
        plain = (node.op_type == "ConvTranspose" and attrs.get("group", 1) == 1
                 and list(attrs.get("dilations", [1, 1])) == [1, 1] and attrs.get("auto_pad", b"NOTSET") == b"NOTSET"
                 and list(attrs.get("kernel_shape", [])) == [3, 3] and node.input[1] in initializers
                 and (len(node.input) < 3 or not node.input[2] or node.input[2] in initializers))  # "": no bias
        strides = list(attrs.get("strides", [1, 1]))
        pads = list(attrs.get("pads", [0, 0, 0, 0]))
        output_padding = list(attrs.get("output_padding", [0, 0]))
        forms = (([2, 2], [1, 1]), ([1, 1], [0, 0])) if subpixel else (([1, 1], [0, 0]),)
        if not plain or pads != [1, 1, 1, 1] or (strides, output_padding) not in forms:
            nodes.append(node)
            continue
        weight = numpy_helper.to_array(initializers[node.input[1]])
        bias = (numpy_helper.to_array(initializers[node.input[2]]) if len(node.input) > 2 and node.input[2]
                else np.zeros(weight.shape[1], weight.dtype))
        name = node.name or node.output[0]
        if strides == [2, 2]:
            conv_weight, conv_bias = subpixel_weights(weight, bias)
            phases = f"{node.output[0]}_phases"
            conv = helper.make_node("Conv", [node.input[0], f"{name}_w", f"{name}_b"], [phases], name=f"{name}_subpixel",
                                    kernel_shape=[2, 2], pads=[0, 0, 1, 1], strides=[1, 1])
            shuffle = helper.make_node("DepthToSpace", [phases], [node.output[0]], name=f"{name}_shuffle",
                                       blocksize=2, mode="CRD")
            nodes.extend([conv, shuffle])
        else:
            conv_weight, conv_bias = np.ascontiguousarray(weight[:, :, ::-1, ::-1].transpose(1, 0, 2, 3)), bias
            nodes.append(helper.make_node("Conv", [node.input[0], f"{name}_w", f"{name}_b"], [node.output[0]],
                                          name=f"{name}_conv", kernel_shape=[3, 3], pads=[1, 1, 1, 1]))
        graph.initializer.extend([numpy_helper.from_array(conv_weight.astype(weight.dtype), f"{name}_w"),
                                  numpy_helper.from_array(conv_bias.astype(weight.dtype), f"{name}_b")])
        rewritten += 1
    _replace_nodes(graph, nodes)
    return model, rewritten


def _replace_nodes(graph: onnx.GraphProto, nodes: list[onnx.NodeProto]) -> None:
    """Set the graph's nodes and drop the initializers no node reads any more."""
    del graph.node[:]
    graph.node.extend(nodes)
    used = {name for node in graph.node for name in node.input}
    kept = [init for init in graph.initializer if init.name in used]
    del graph.initializer[:]
    graph.initializer.extend(kept)


def _splice(graph: onnx.GraphProto, replacements: dict[str, list[onnx.NodeProto]], dropped: set[str]) -> None:
    """Put each node keyed (by name, or first output when unnamed) in ``replacements`` by its list, leave out
    those in ``dropped``, and forget the inferred shapes."""
    nodes = []
    for node in graph.node:
        key = node.name or node.output[0]
        if key in replacements:
            nodes.extend(replacements[key])
        elif key not in dropped:
            nodes.append(node)
    _replace_nodes(graph, nodes)
    del graph.value_info[:]


def _plain_conv(node: onnx.NodeProto, initializers: dict) -> bool:
    """A group-1 Conv whose weights (and bias) are stored in the graph."""
    return (node.op_type == "Conv" and _attributes(node).get("group", 1) == 1
            and all(name in initializers for name in node.input[1:] if name))


def _consumers(graph: onnx.GraphProto) -> defaultdict[str, list[onnx.NodeProto]]:
    """The nodes reading each tensor, by tensor name (in graph order)."""
    consumers = defaultdict(list)
    for node in graph.node:
        for name in node.input:
            consumers[name].append(node)
    return consumers


def _input_conv_weights(graph: onnx.GraphProto):
    """A function giving a node's weight array when it is a plain (group 1) Conv reading a graph input, else
    None: the convs :func:`split_input_convs` and :func:`pad_input_convs` rewrite."""
    initializers = {init.name: init for init in graph.initializer}
    graph_inputs = {value.name for value in graph.input} - set(initializers)

    def weight(node: onnx.NodeProto) -> np.ndarray | None:
        if (node.op_type != "Conv" or node.input[0] not in graph_inputs or node.input[1] not in initializers
                or _attributes(node).get("group", 1) != 1):
            return None
        return numpy_helper.to_array(initializers[node.input[1]])

    return weight


def split_input_convs(model: onnx.ModelProto, block: int = 16) -> tuple[onnx.ModelProto, int]:
    """A copy of ``model`` where each plain Conv reading a graph input with C ≥ ``block`` channels,
    C not a multiple of ``block``, is split into a conv on channels [0, C − C mod block) and one on
    the rest, summed (the bias goes with the first). Returns the new model and the number split.
    """
    model = onnx.ModelProto.FromString(model.SerializeToString())
    graph = model.graph
    input_conv_weight = _input_conv_weights(graph)
    nodes, split = [], 0
    for node in graph.node:
        attrs = _attributes(node)
        weight = input_conv_weight(node)
        channels = weight.shape[1] if weight is not None else 0
        if channels < block or channels % block == 0:
            nodes.append(node)
            continue
        aligned = channels - channels % block
        name = node.name or node.output[0]
        bounds = {f"{name}_c0": 0, f"{name}_c1": aligned, f"{name}_c2": channels, f"{name}_axis": 1}
        graph.initializer.extend(numpy_helper.from_array(np.array([v], np.int64), k) for k, v in bounds.items())
        graph.initializer.extend([numpy_helper.from_array(np.ascontiguousarray(weight[:, :aligned]), f"{name}_wa"),
                                  numpy_helper.from_array(np.ascontiguousarray(weight[:, aligned:]), f"{name}_wb")])
        bias = list(node.input[2:3])
        nodes.extend([
            helper.make_node("Slice", [node.input[0], f"{name}_c0", f"{name}_c1", f"{name}_axis"], [f"{name}_xa"],
                             name=f"{name}_slice_a"),
            helper.make_node("Slice", [node.input[0], f"{name}_c1", f"{name}_c2", f"{name}_axis"], [f"{name}_xb"],
                             name=f"{name}_slice_b"),
            helper.make_node("Conv", [f"{name}_xa", f"{name}_wa", *bias], [f"{name}_ya"], name=f"{name}_a", **attrs),
            helper.make_node("Conv", [f"{name}_xb", f"{name}_wb"], [f"{name}_yb"], name=f"{name}_b", **attrs),
            helper.make_node("Add", [f"{name}_ya", f"{name}_yb"], [node.output[0]], name=f"{name}_sum"),
        ])
        split += 1
    _replace_nodes(graph, nodes)
    return model, split


def merge_split_input_convs(model: onnx.ModelProto, skip: frozenset[str] = frozenset()
                            ) -> tuple[onnx.ModelProto, int]:
    """The inverse of :func:`split_input_convs`: each Slice–Slice–Conv–Conv–Add group it made becomes the one
    Conv on the whole graph input again (weights concatenated, the first part's bias), except groups with a
    node named in ``skip``. Returns the new model and the number merged. Exact: the same multiply-adds.
    """
    model = onnx.ModelProto.FromString(model.SerializeToString())
    graph = model.graph
    initializers = {init.name: init for init in graph.initializer}
    by_name = {node.name: node for node in graph.node}
    merged: dict[str, onnx.NodeProto] = {}  # name of the group's first node → the merged conv
    dropped: set[str] = set()
    for node in graph.node:
        name = node.name.removesuffix("_sum")
        group = [by_name.get(f"{name}{suffix}") for suffix in ("_slice_a", "_slice_b", "_a", "_b")]
        if node.op_type != "Add" or not node.name.endswith("_sum") or None in group or node.name in skip:
            continue
        slice_a, slice_b, conv_a, conv_b = group
        if (any(n.name in skip for n in group) or slice_a.input[0] != slice_b.input[0]
                or list(node.input) != [conv_a.output[0], conv_b.output[0]]
                or conv_a.input[0] != slice_a.output[0] or conv_b.input[0] != slice_b.output[0]):
            continue
        weight = np.concatenate([numpy_helper.to_array(initializers[conv_a.input[1]]),
                                 numpy_helper.to_array(initializers[conv_b.input[1]])], axis=1)
        graph.initializer.append(numpy_helper.from_array(weight, f"{name}_w"))
        merged[slice_a.name] = helper.make_node("Conv", [slice_a.input[0], f"{name}_w", *conv_a.input[2:3]],
                                                [node.output[0]], name=name, **_attributes(conv_a))
        dropped.update(n.name for n in (*group, node))
    nodes = [merged.get(node.name, node) for node in graph.node if node.name in merged or node.name not in dropped]
    _replace_nodes(graph, nodes)
    return model, len(merged)


def pad_input_convs(model: onnx.ModelProto, multiple: int = 4, skip: frozenset[str] = frozenset()
                    ) -> tuple[onnx.ModelProto, int]:
    """A copy of ``model`` where each plain Conv reading a graph input whose channel count is not a multiple
    of ``multiple`` reads it through a Pad with zero channels up to the next multiple, with zero input
    weights for them: exact. Convs named in ``skip`` stay as they are. Returns the new model and the number
    padded.

    For INT8 (module docstring, 7): VNNI multiplies groups of four uint8 values.
    """
    model = onnx.ModelProto.FromString(model.SerializeToString())
    graph = model.graph
    input_conv_weight = _input_conv_weights(graph)
    nodes, padded = [], 0
    for node in graph.node:
        weight = input_conv_weight(node)
        if weight is None or node.name in skip or weight.shape[1] % multiple == 0:
            nodes.append(node)
            continue
        extra = multiple - weight.shape[1] % multiple
        name = node.name or node.output[0]
        pads = np.zeros(2 * weight.ndim, np.int64)
        pads[weight.ndim + 1] = extra  # after the last channel (axis 1 of NCHW)
        padded_weight = np.concatenate([weight, np.zeros((weight.shape[0], extra, *weight.shape[2:]), weight.dtype)],
                                       axis=1)
        graph.initializer.extend([numpy_helper.from_array(pads, f"{name}_channel_pads"),
                                  numpy_helper.from_array(padded_weight, f"{name}_w_padded")])
        nodes.append(helper.make_node("Pad", [node.input[0], f"{name}_channel_pads"], [f"{name}_x_padded"],
                                      name=f"{name}_pad", mode="constant"))
        conv = onnx.NodeProto()
        conv.CopyFrom(node)
        conv.input[0], conv.input[1] = f"{name}_x_padded", f"{name}_w_padded"
        nodes.append(conv)
        padded += 1
    _replace_nodes(graph, nodes)
    del graph.value_info[:]
    return model, padded


def quantize_before_pad(model: onnx.ModelProto) -> tuple[onnx.ModelProto, int]:
    """A copy of a quantized ``model`` where each constant Pad (pad value 0) whose only reader is a
    QuantizeLinear is moved after it, padding the uint8 tensor with the zero point instead: q(0) is the
    zero point exactly, so the output is the same, and the Pad moves a quarter of the bytes. Returns the
    new model and the number moved.
    """
    model = onnx.ModelProto.FromString(model.SerializeToString())
    graph = model.graph
    consumers = _consumers(graph)
    scalars = {init.name for init in graph.initializer if int(np.prod(init.dims)) == 1}
    outputs = {value.name for value in graph.output}
    replacement: dict[str, list[onnx.NodeProto]] = {}  # a moved Pad's name → the pair in its new order
    skipped: set[str] = set()
    for pad in graph.node:
        readers = consumers[pad.output[0]]
        if (pad.op_type != "Pad" or _attributes(pad).get("mode", b"constant") != b"constant" or len(pad.input) > 2
                or pad.output[0] in outputs or len(readers) != 1 or readers[0].op_type != "QuantizeLinear"
                or not set(readers[0].input[1:3]) <= scalars):  # per-tensor scale and zero point only
            continue
        quantize, padded = readers[0], readers[0].output[0]
        moved_q, moved_pad = onnx.NodeProto(), onnx.NodeProto()
        moved_q.CopyFrom(quantize)
        moved_q.input[0], moved_q.output[0] = pad.input[0], f"{padded}_unpadded"
        moved_pad.CopyFrom(pad)
        del moved_pad.input[:]
        # Pad with the zero point; without one (its default is 0) the Pad's own default 0 is q(0).
        moved_pad.input.extend([f"{padded}_unpadded", pad.input[1], *quantize.input[2:3]])
        moved_pad.output[0] = padded
        replacement[pad.name] = [moved_q, moved_pad]
        skipped.add(quantize.name)
    nodes = [n for node in graph.node if node.name not in skipped for n in replacement.get(node.name, [node])]
    _replace_nodes(graph, nodes)
    del graph.value_info[:]
    return model, len(replacement)


_ELEMENTWISE_ZERO_KEEPING = ("Relu", "LeakyRelu")  # f(0) = 0: padded channels stay zero through them


def pad_narrow_convs(model: onnx.ModelProto, block: int = 16) -> tuple[onnx.ModelProto, int]:
    """A copy of ``model`` where each Conv with fewer than ``block`` output channels, whose output reaches
    only plain Convs (directly or through one Relu/LeakyRelu), gets zero output channels up to ``block``
    and its consumers matching zero input weights. Returns the new model and the number padded.

    The padded channels are exactly zero (zero weights and bias, then f(0) = 0) and are read with zero
    weights, so outputs are unchanged.
    """
    model = onnx.ModelProto.FromString(model.SerializeToString())
    graph = model.graph
    initializers = {init.name: init for init in graph.initializer}
    consumers = _consumers(graph)
    outputs = {value.name for value in graph.output}


    def readers(node: onnx.NodeProto) -> list[onnx.NodeProto] | None:
        """The Convs reading the node's output as their data (through one zero-keeping activation);
        None when anything else reads it."""
        found = []
        for user in consumers[node.output[0]]:
            if user.op_type in _ELEMENTWISE_ZERO_KEEPING and user.output[0] not in outputs:
                found.extend((user.output[0], reader) for reader in consumers[user.output[0]])
            else:
                found.append((node.output[0], user))
        if not found or not all(_plain_conv(reader, initializers) and reader.input[0] == tensor for tensor, reader in found):
            return None
        return [reader for _, reader in found]

    def replace(name: str, array: np.ndarray) -> None:
        initializers[name].CopyFrom(numpy_helper.from_array(array.astype(np.float32), name))

    padded = 0
    for node in graph.node:
        if not _plain_conv(node, initializers) or node.output[0] in outputs:
            continue
        weight = numpy_helper.to_array(initializers[node.input[1]])
        narrow = weight.shape[0]
        users = readers(node)
        if narrow >= block or users is None:
            continue
        touched = [node.input[1], *node.input[2:3], *(u.input[1] for u in users)]
        if any(len(consumers[name]) != 1 for name in touched if name):
            continue  # an initializer shared between nodes cannot be padded for one of them alone
        extra = block - narrow
        replace(node.input[1], np.concatenate([weight, np.zeros((extra, *weight.shape[1:]), weight.dtype)]))
        if len(node.input) > 2 and node.input[2]:
            bias = numpy_helper.to_array(initializers[node.input[2]])
            replace(node.input[2], np.concatenate([bias, np.zeros(extra, bias.dtype)]))
        for user in users:
            w = numpy_helper.to_array(initializers[user.input[1]])
            zeros = np.zeros((w.shape[0], extra, *w.shape[2:]), w.dtype)
            replace(user.input[1], np.concatenate([w, zeros], axis=1))
        padded += 1
    # Shapes recorded by an earlier inference are stale for the padded tensors.
    del graph.value_info[:]
    return model, padded


# Ops whose output is finite wherever their data inputs are (for a Clip: its input; bounds are constants).
_FINITE_PRESERVING = ("Clip", "MaxPool", "Relu", "LeakyRelu", "Max", "Min", "Where", "Identity")


def where_as_arithmetic(model: onnx.ModelProto) -> tuple[onnx.ModelProto, int]:
    """A copy of ``model`` where each float32 ``Where(c, a, b)`` whose branches are finite for finite graph
    inputs becomes ``a·float(c) + b·float(not c)``. Returns the new model and the number rewritten.

    ONNX Runtime's CPU ``Where`` runs one element at a time: on the edge depth net's 176 × 608 prefill
    maps a Greater + Where took 0.53 ms against 0.07 for the arithmetic form (6 of them, a twentieth of
    the net). For finite a and b the two are equal (x·1 = x, x·0 = ±0, x + ±0 = x); an infinite branch
    would give NaN (∞·0), so a branch counts as finite only when it provably is: a constant with finite
    values, a graph input (the runtime refuses non-finite inputs), the reciprocal of a Clip with a
    positive minimum whose own reciprocal float32 can hold (1/1e-45 cannot), or a finite-preserving op
    (Clip, MaxPool, Relu, Max, Where, …) of finite inputs.
    """
    model = onnx.ModelProto.FromString(model.SerializeToString())
    graph = model.graph
    initializers = {init.name: init for init in graph.initializer}
    producers = {name: node for node in graph.node for name in node.output}
    graph_inputs = {value.name for value in graph.input}
    inferred = onnx.shape_inference.infer_shapes(model)
    elem_type = {v.name: v.type.tensor_type.elem_type
                 for v in [*inferred.graph.value_info, *inferred.graph.input, *inferred.graph.output]}
    elem_type.update({name: init.data_type for name, init in initializers.items()})
    memo: dict[str, bool] = {}

    def positive_constant(name: str) -> bool:
        """A constant whose reciprocal is finite: positive, and not so small (below 1/FLT_MAX) that 1/x overflows."""
        if name not in initializers:
            return False
        values = numpy_helper.to_array(initializers[name])
        with np.errstate(divide="ignore", over="ignore"):
            return bool((values > 0).all() and np.isfinite(np.reciprocal(values)).all())

    def finite(name: str) -> bool:
        if name not in memo:
            memo[name] = False  # a cycle (impossible in a valid graph) proves nothing
            if name in initializers:
                memo[name] = bool(np.isfinite(numpy_helper.to_array(initializers[name])).all())
            elif name in graph_inputs:
                memo[name] = True
            elif name in producers:
                node = producers[name]
                if node.op_type == "Reciprocal":
                    clip = producers.get(node.input[0])
                    memo[name] = (clip is not None and clip.op_type == "Clip" and len(clip.input) > 1
                                  and positive_constant(clip.input[1]) and finite(clip.input[0]))
                elif node.op_type in _FINITE_PRESERVING:
                    data = {"Where": node.input[1:], "Max": node.input, "Min": node.input}.get(node.op_type,
                                                                                             node.input[:1])
                    memo[name] = all(finite(i) for i in data if i)
        return memo[name]

    nodes, rewritten = [], 0
    for node in graph.node:
        if (node.op_type != "Where" or elem_type.get(node.output[0]) != onnx.TensorProto.FLOAT
                or not (finite(node.input[1]) and finite(node.input[2]))):
            nodes.append(node)
            continue
        cond, a, b = node.input
        name = node.name or node.output[0]
        nodes.extend([
            helper.make_node("Cast", [cond], [f"{name}_take_a"], to=onnx.TensorProto.FLOAT, name=f"{name}_cast_a"),
            helper.make_node("Not", [cond], [f"{name}_not"], name=f"{name}_not"),
            helper.make_node("Cast", [f"{name}_not"], [f"{name}_take_b"], to=onnx.TensorProto.FLOAT,
                             name=f"{name}_cast_b"),
            helper.make_node("Mul", [a, f"{name}_take_a"], [f"{name}_a"], name=f"{name}_mul_a"),
            helper.make_node("Mul", [b, f"{name}_take_b"], [f"{name}_b"], name=f"{name}_mul_b"),
            helper.make_node("Add", [f"{name}_a", f"{name}_b"], [node.output[0]], name=f"{name}_sum"),
        ])
        rewritten += 1
    _replace_nodes(graph, nodes)
    return model, rewritten


def merge_parallel_convs(model: onnx.ModelProto) -> tuple[onnx.ModelProto, int]:
    """A copy of ``model`` where each channel ``Concat`` of ``Relu(Conv(x_i))`` branches, the convs alike
    but for their channels, becomes one ``Relu(Conv(Concat(x_i)))`` with block-diagonal weights.
    Returns the new model and the number merged.

    The depth net's early fusion is such a Concat (module docstring, 6). The cross weights are exact
    zeros, so the sums are the same up to float summation order. Branches whose convs differ in
    anything but channels (the ASPP's dilations) stay as they are.
    """
    model = onnx.ModelProto.FromString(model.SerializeToString())
    graph = model.graph
    initializers = {init.name: init for init in graph.initializer}
    producers = {name: node for node in graph.node for name in node.output}
    uses = defaultdict(int)
    for node in graph.node:
        for name in node.input:
            uses[name] += 1
    outputs = {value.name for value in graph.output}

    def branch(name: str) -> tuple[onnx.NodeProto, onnx.NodeProto] | None:
        """(Relu, Conv) producing ``name``, each read only by the next step, with constant weights."""
        relu = producers.get(name)
        conv = producers.get(relu.input[0]) if relu is not None and relu.op_type == "Relu" else None
        if (conv is None or conv.op_type != "Conv" or uses[relu.output[0]] != 1 or uses[conv.output[0]] != 1
                or name in outputs or not all(n in initializers and uses[n] == 1 for n in conv.input[1:] if n)):
            return None
        return relu, conv

    merged_away: set[str] = set()
    replacements: dict[str, list[onnx.NodeProto]] = {}
    for node in graph.node:
        if node.op_type != "Concat" or _attributes(node).get("axis") != 1 or len(node.input) < 2:
            continue
        branches = [branch(name) for name in node.input]
        if any(b is None for b in branches):
            continue
        convs = [conv for _, conv in branches]
        attrs = [_attributes(conv) for conv in convs]
        if any(a != attrs[0] for a in attrs) or attrs[0].get("group", 1) != 1:
            continue
        weights = [numpy_helper.to_array(initializers[conv.input[1]]) for conv in convs]
        biases = [numpy_helper.to_array(initializers[conv.input[2]]) if len(conv.input) > 2 and conv.input[2]
                  else np.zeros(w.shape[0], np.float32) for conv, w in zip(convs, weights)]
        weight = np.zeros((sum(w.shape[0] for w in weights), sum(w.shape[1] for w in weights),
                           *weights[0].shape[2:]), np.float32)
        row = col = 0
        for w in weights:
            weight[row:row + w.shape[0], col:col + w.shape[1]] = w
            row, col = row + w.shape[0], col + w.shape[1]
        name = node.name or node.output[0]
        graph.initializer.extend([numpy_helper.from_array(weight, f"{name}_merged_w"),
                                  numpy_helper.from_array(np.concatenate(biases).astype(np.float32), f"{name}_merged_b")])
        replacements[node.name or node.output[0]] = [
            helper.make_node("Concat", [conv.input[0] for conv in convs], [f"{name}_merged_x"], axis=1,
                             name=f"{name}_merged_inputs"),
            helper.make_node("Conv", [f"{name}_merged_x", f"{name}_merged_w", f"{name}_merged_b"],
                             [f"{name}_merged_y"], name=f"{name}_merged_conv", **attrs[0]),
            helper.make_node("Relu", [f"{name}_merged_y"], [node.output[0]], name=f"{name}_merged_relu"),
        ]
        merged_away.update(n.name or n.output[0] for pair in branches for n in pair)
    _splice(graph, replacements, merged_away)
    return model, len(replacements)


def value_shape(value: onnx.ValueInfoProto) -> list[int | str]:
    """A graph input's or output's shape: sizes, or the names of symbolic dimensions."""
    return [d.dim_value if d.HasField("dim_value") else d.dim_param for d in value.type.tensor_type.shape.dim]


def _constant_ints(initializers: dict[str, onnx.TensorProto], name: str) -> list[int] | None:
    """The values of an int64 initializer, or None when ``name`` is not one."""
    if name not in initializers or initializers[name].data_type != onnx.TensorProto.INT64:
        return None
    return [int(v) for v in numpy_helper.to_array(initializers[name]).reshape(-1)]


def inputs_from_channel_slices(model: onnx.ModelProto) -> tuple[onnx.ModelProto, int]:
    """A copy of ``model`` where each graph input read only by Slices along axis 1 that tile its channels
    (constant bounds, step 1, no overlap, no gap) is replaced by one graph input per slice, named
    ``input[lo:hi]`` (module docstring, 8). Returns the new model and the number of inputs replaced.
    """
    model = onnx.ModelProto.FromString(model.SerializeToString())
    graph = model.graph
    initializers = {init.name: init for init in graph.initializer}
    consumers = _consumers(graph)
    outputs = {value.name for value in graph.output}
    new_inputs, renamed, dropped, replaced = [], {}, set(), 0
    for value in graph.input:
        dims = value.type.tensor_type.shape.dim
        readers = consumers[value.name]
        if value.name in initializers or len(dims) < 2 or not dims[1].HasField("dim_value") or not readers:
            new_inputs.append(value)
            continue
        ranges = []
        for node in readers:
            bounds = [_constant_ints(initializers, name) for name in node.input[1:]]
            if (node.op_type != "Slice" or node.input[0] != value.name or len(bounds) < 3 or None in bounds
                    or any(len(b) != 1 for b in bounds) or bounds[2] != [1]
                    or (len(bounds) > 3 and bounds[3] != [1]) or node.output[0] in outputs):
                break
            ranges.append((bounds[0][0], bounds[1][0], node))
        else:
            ranges.sort(key=lambda r: r[0])
            if tiles([r[:2] for r in ranges]) and ranges[-1][1] == dims[1].dim_value:
                for lo, hi, node in ranges:
                    piece = piece_name(value.name, lo, hi)
                    shape = value_shape(value)
                    shape[1] = hi - lo
                    new_inputs.append(helper.make_tensor_value_info(piece, value.type.tensor_type.elem_type, shape))
                    renamed[node.output[0]] = piece
                    dropped.add(node.name or node.output[0])
                replaced += 1
                continue
        new_inputs.append(value)
    if not replaced:
        return model, 0
    nodes = [node for node in graph.node if (node.name or node.output[0]) not in dropped]
    for node in nodes:
        for k, name in enumerate(node.input):
            node.input[k] = renamed.get(name, name)
    _replace_nodes(graph, nodes)
    del graph.input[:]
    graph.input.extend(new_inputs)
    del graph.value_info[:]
    return model, replaced


def inputs_from_channel_pieces(model: onnx.ModelProto) -> tuple[onnx.ModelProto, int]:
    """The inverse of :func:`inputs_from_channel_slices`: graph inputs named ``input[lo:hi]`` that tile
    ``input``'s channels become one graph input again, read through Slices named ``<reader>_slice_a`` and
    ``_slice_b`` after a conv reader ``<reader>_a`` / ``_b`` (as :func:`split_input_convs` named them, so
    :func:`merge_split_input_convs` finds them). Returns the new model and the number of inputs joined.
    """
    model = onnx.ModelProto.FromString(model.SerializeToString())
    graph = model.graph
    consumers = _consumers(graph)
    pieces: dict[str, list[tuple[int, int, onnx.ValueInfoProto]]] = {}
    for value in graph.input:
        piece = channel_piece(value.name)
        if piece is not None:
            pieces.setdefault(piece[0], []).append((piece[1], piece[2], value))
    slices, joined = [], {}
    for base, parts in pieces.items():
        parts.sort(key=lambda p: p[0])
        if not tiles([p[:2] for p in parts]):
            continue
        first = parts[0][2]
        dims = value_shape(first)
        dims[1] = parts[-1][1]
        joined[base] = (helper.make_tensor_value_info(base, first.type.tensor_type.elem_type, dims),
                        {p[2].name for p in parts})
        for lo, hi, value in parts:
            readers = consumers[value.name]
            reader = readers[0].name if len(readers) == 1 else ""
            stem, suffix = (reader[:-2], reader[-1]) if reader[-2:] in ("_a", "_b") else (value.name, "x")
            bounds = {f"{stem}_c{suffix}_lo": lo, f"{stem}_c{suffix}_hi": hi, f"{stem}_c{suffix}_axis": 1}
            graph.initializer.extend(numpy_helper.from_array(np.array([v], np.int64), k) for k, v in bounds.items())
            slices.append(helper.make_node("Slice", [base, *bounds], [value.name], name=f"{stem}_slice_{suffix}"))
    if not joined:
        return model, 0
    inputs, placed = [], set()
    for value in graph.input:
        base = next((b for b, (_, names) in joined.items() if value.name in names), None)
        if base is None:
            inputs.append(value)
        elif base not in placed:
            inputs.append(joined[base][0])
            placed.add(base)
    _replace_nodes(graph, slices + list(graph.node))
    del graph.input[:]
    graph.input.extend(inputs)
    del graph.value_info[:]
    return model, len(joined)


_UNARY_HEAD_OPS = ("Sigmoid", "Tanh", "Relu", "Exp", "Identity")  # what may stand between a head and its output


def merge_output_heads(model: onnx.ModelProto) -> tuple[onnx.ModelProto, int]:
    """A copy of ``model`` where the plain Convs reading one tensor whose outputs are graph outputs (directly
    or through one unary op such as a Sigmoid) become one Conv with their output channels side by side and
    a Split back into the original outputs (module docstring, 9). Returns the new model and the number of
    convs merged away. Exact: each output channel keeps its own weights and bias.
    """
    model = onnx.ModelProto.FromString(model.SerializeToString())
    graph = model.graph
    initializers = {init.name: init for init in graph.initializer}
    consumers = _consumers(graph)
    outputs = {value.name for value in graph.output}

    def is_head(node: onnx.NodeProto) -> bool:
        if not _plain_conv(node, initializers):
            return False
        out = node.output[0]
        readers = consumers[out]
        if out in outputs:
            return not readers
        return (len(readers) == 1 and readers[0].op_type in _UNARY_HEAD_OPS
                and readers[0].output[0] in outputs and not consumers[readers[0].output[0]])

    groups: dict[tuple, list[onnx.NodeProto]] = defaultdict(list)
    for node in graph.node:
        if is_head(node):
            groups[(node.input[0], repr(sorted(_attributes(node).items())))].append(node)
    replacements: dict[str, list[onnx.NodeProto]] = {}
    dropped: set[str] = set()
    for heads in groups.values():
        if len(heads) < 2:
            continue
        weights = [numpy_helper.to_array(initializers[h.input[1]]) for h in heads]
        biases = [numpy_helper.to_array(initializers[h.input[2]]) if len(h.input) > 2 and h.input[2]
                  else np.zeros(w.shape[0], w.dtype) for h, w in zip(heads, weights)]
        # "<heads>_heads_w" and "_sizes" tell models/onnx_weights.py where each head's weights went.
        name = "_".join(h.name or h.output[0] for h in heads) + "_heads"
        graph.initializer.extend([
            numpy_helper.from_array(np.concatenate(weights), f"{name}_w"),
            numpy_helper.from_array(np.concatenate(biases).astype(weights[0].dtype), f"{name}_b"),
            numpy_helper.from_array(np.array([w.shape[0] for w in weights], np.int64), f"{name}_sizes"),
        ])
        replacements[heads[0].name or heads[0].output[0]] = [
            helper.make_node("Conv", [heads[0].input[0], f"{name}_w", f"{name}_b"], [name], name=name,
                             **_attributes(heads[0])),
            helper.make_node("Split", [name, f"{name}_sizes"], [h.output[0] for h in heads], name=f"{name}_split",
                             axis=1),
        ]
        dropped.update(h.name or h.output[0] for h in heads[1:])
    _splice(graph, replacements, dropped)
    return model, len(dropped)


def lower_for_cpu(model: onnx.ModelProto) -> tuple[onnx.ModelProto, dict[str, int]]:
    """The exact fp32 rewrites (module docstring, 1 to 3, 5, 6, 8 and 9); returns the model and how many nodes
    (graph inputs for 8) each changed."""
    model, transposed = rewrite_transposed_convs(model, subpixel=False)
    model, merged = merge_parallel_convs(model)
    model, split = split_input_convs(model)
    model, padded = pad_narrow_convs(model)
    model, wheres = where_as_arithmetic(model)
    model, pieces = inputs_from_channel_slices(model)
    model, heads = merge_output_heads(model)
    return model, {"stride1_transposed_convs": transposed, "merged_parallel_convs": merged,
                   "split_input_convs": split, "padded_narrow_convs": padded, "where_as_arithmetic": wheres,
                   "inputs_in_channel_pieces": pieces, "merged_output_heads": heads}


def boundary_nodes(model: onnx.ModelProto, inputs: bool = True, outputs: bool = True,
                   output_convs: int = 1) -> list[str]:
    """Names of the nodes between each graph input and its first Conv (``inputs``), and between the
    ``output_convs``-th last Conv on each path and each output (``outputs``).

    The Convs themselves are included: the first layer reads the raw input, the last one writes the output.
    """
    consumers, producer = defaultdict(list), {}
    for node in model.graph.node:
        for name in node.input:
            consumers[name].append(node)
        for name in node.output:
            producer[name] = node
    chosen: set[str] = set()

    def walk(start: list[onnx.NodeProto], step, convs: int = 1) -> None:
        # Each walk keeps its own visited set: a node both walks reach (the depth net's filled input
        # is added to its output) must not stop the second walk before it reaches its conv.
        stack, seen = [(node, convs) for node in start], set()
        while stack:
            node, left = stack.pop()
            if node.name in seen:
                continue
            seen.add(node.name)
            left -= node.op_type == "Conv"
            if left > 0:
                stack.extend((n, left) for n in step(node))
        chosen.update(seen)

    initializers = {init.name for init in model.graph.initializer}
    if inputs:
        walk([n for i in model.graph.input if i.name not in initializers for n in consumers[i.name]],
             lambda node: [n for out in node.output for n in consumers[out]])
    if outputs:
        walk([producer[o.name] for o in model.graph.output if o.name in producer],
             lambda node: [producer[i] for i in node.input if i in producer], output_convs)
    return sorted(chosen)
