"""What FP16 can hold: the nodes an FP16 conversion keeps in FP32, and a check of what it stores in FP16.

ONNX Runtime's CPU provider runs most FP16 nodes in FP32 (it casts around them and drops the casts between
them), so a CPU run of a converted graph does not show what GPU FP16 kernels compute. The edge depth net
shows the difference: its prefill's ``Where`` is arithmetic (export/rewrite.py, 5), ``a·c + b·(1 − c)``
with ``a = 1/clip(x, 1e-6)``, which is 1e6 wherever the prefilled map is still empty (a third of each
bundled frame's pixels). FP16 stores that as ∞, and ∞·0 is NaN on a GPU: the NaNs spread over the whole
depth map. Nothing about the ops says so; the values do.

So the conversion runs the FP32 graph on real frames with every tensor exposed (:func:`fp16_ranges`) and
keeps in FP32 the producer and every reader of a tensor that FP16 cannot hold (:func:`fp16_unsafe_nodes`):

* a value beyond ±65504 (stored as ±∞), or
* a divisor (of ``Div`` or ``Reciprocal``) with nonzero values below FP16's smallest normal number,
  6.1e-5: FP16 keeps them with fewer bits, and none below 3e-8 (they become 0 and the quotient ∞);
  a GPU that flushes subnormals makes them all 0. Elsewhere such a value is an absolute error below
  6.1e-5, which does not matter.

ONNX Runtime's converter puts an FP16 Cast after every output of a node it keeps FP32 and one back before
every input, so between two such nodes a tensor still passes through FP16; :func:`drop_fp16_round_trips`
lets them read each other's FP32 outputs. :func:`check_fp16_storage` then casts the FP32 values of every
tensor the converted graph holds in FP16 to float16 and fails, naming the node, when one becomes ±∞ (or a
divisor leaves the normal range): a later graph rewrite that overflows stops the conversion instead of
shipping NaNs. :func:`sort_topologically` restores the node order the converter leaves unsorted.
"""

from __future__ import annotations

import heapq
import math
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from pipeline.graph_inputs import feeds_for

FP16_MAX = float(np.finfo(np.float16).max)  # 65504: larger magnitudes are stored as ±inf (from 65520 on)
FP16_SMALLEST_NORMAL = float(np.finfo(np.float16).tiny)  # 2⁻¹⁴ ≈ 6.1e-05
DIVISOR_INPUT = {"Div": 1, "Reciprocal": 0}  # the input whose small values make the output large


class FP16RangeError(ValueError):
    """A tensor the FP16 graph holds in float16 takes values float16 cannot hold."""


@dataclass
class Fp16Range:
    """How one FP32 tensor's values fare stored as float16, over all frames seen."""

    largest: float = 0.0  # max |x|
    smallest: float = math.inf  # min nonzero |x|
    overflow: int = 0  # finite values float16 stores as ±inf
    subnormal: int = 0  # nonzero values float16 stores as subnormals or as 0

    def add(self, values: np.ndarray) -> None:
        """Count in one array (float16 storage emulated by a cast)."""
        magnitude = np.abs(values, dtype=np.float32)
        with np.errstate(over="ignore"):
            stored = magnitude.astype(np.float16)
        nonzero = magnitude > 0
        self.largest = max(self.largest, float(magnitude.max(initial=0.0)))
        self.smallest = min(self.smallest, float(magnitude.min(initial=np.inf, where=nonzero)))
        self.overflow += int(np.count_nonzero(np.isinf(stored) & np.isfinite(magnitude)))
        self.subnormal += int(np.count_nonzero(nonzero & (stored < FP16_SMALLEST_NORMAL)))

    def trouble(self, divisor_of: str | None = None) -> str | None:
        """Why FP16 cannot hold the tensor (``divisor_of``: the node dividing by it, if any), or None."""
        if self.overflow:
            return f"{self.overflow} values beyond FP16's ±{FP16_MAX:.0f} (|x| up to {self.largest:.3g})"
        if divisor_of is not None and self.subnormal:
            return (f"{self.subnormal} nonzero values below FP16's smallest normal {FP16_SMALLEST_NORMAL:.2g} "
                    f"(|x| down to {self.smallest:.3g}), and {divisor_of} divides by it")
        return None


def _elem_types(model: onnx.ModelProto) -> dict[str, int]:
    """Element type of every tensor of ``model`` whose type is known (after shape inference)."""
    inferred = onnx.shape_inference.infer_shapes(model)
    graph = inferred.graph
    types = {v.name: v.type.tensor_type.elem_type for v in [*graph.value_info, *graph.input, *graph.output]}
    types.update({init.name: init.data_type for init in graph.initializer})
    return types


def fp16_ranges(model: onnx.ModelProto, feeds: Iterable[dict[str, np.ndarray]]) -> dict[str, Fp16Range]:
    """Each float32 tensor of ``model`` (inputs, initializers, every node output) on ``feeds``, as float16 would
    store it. Runs the FP32 graph with every intermediate tensor exposed as an output: per frame that holds
    them all at once (0.12 GB for the edge depth net, 0.22 GB for PIXOR), but keeps only the counts."""
    import onnxruntime as ort

    types = _elem_types(model)
    exposed = onnx.ModelProto.FromString(model.SerializeToString())
    listed = {value.name for value in exposed.graph.output}
    for node in exposed.graph.node:
        exposed.graph.output.extend(helper.make_tensor_value_info(name, TensorProto.FLOAT, None)
                                    for name in node.output
                                    if name and name not in listed and types.get(name) == TensorProto.FLOAT)
    ranges: defaultdict[str, Fp16Range] = defaultdict(Fp16Range)
    for init in model.graph.initializer:
        if init.data_type == TensorProto.FLOAT:
            ranges[init.name].add(numpy_helper.to_array(init))
    session = ort.InferenceSession(exposed.SerializeToString(), providers=["CPUExecutionProvider"])
    names = [output.name for output in session.get_outputs()]
    for feed in feeds:
        arrays = feeds_for(session, {k: v.astype(np.float32) for k, v in feed.items()})
        for name, values in [*arrays.items(), *zip(names, session.run(None, arrays), strict=True)]:
            if values.dtype == np.float32:
                ranges[name].add(values)
    return dict(ranges)


def _divisors(graph: onnx.GraphProto) -> dict[str, str]:
    """Tensor name → the name of a node dividing by it."""
    return {node.input[DIVISOR_INPUT[node.op_type]]: node.name for node in graph.node
            if node.op_type in DIVISOR_INPUT and len(node.input) > DIVISOR_INPUT[node.op_type]}


def fp16_unsafe_nodes(model: onnx.ModelProto, ranges: dict[str, Fp16Range]) -> dict[str, str]:
    """Node name → why it stays FP32: it writes or reads a tensor FP16 cannot hold on the frames of ``ranges``.

    Both ends of such a tensor stay FP32, so (with :func:`drop_fp16_round_trips`) it is never stored in FP16."""
    divisors = _divisors(model.graph)
    readers: defaultdict[str, list[str]] = defaultdict(list)
    producer: dict[str, str] = {}
    for node in model.graph.node:
        for name in node.input:
            readers[name].append(node.name)
        producer.update({name: node.name for name in node.output})
    reasons: defaultdict[str, list[str]] = defaultdict(list)
    for tensor, values in ranges.items():
        why = values.trouble(divisors.get(tensor))
        if why is None:
            continue
        if tensor in producer:
            reasons[producer[tensor]].append(f"writes {tensor}: {why}")
        for node in dict.fromkeys(readers[tensor]):  # a node reading a tensor twice says so once
            reasons[node].append(f"reads {tensor}: {why}")
    return {node: "; ".join(why) for node, why in reasons.items()}


def name_nodes(model: onnx.ModelProto) -> int:
    """Name every unnamed node (the converter keeps nodes FP32 by name); returns how many were named."""
    taken = {node.name for node in model.graph.node}
    named = 0
    for index, node in enumerate(model.graph.node):
        if not node.name:
            name, k = f"{node.op_type}_{index}", 0
            while name in taken:
                k += 1
                name = f"{node.op_type}_{index}_{k}"
            node.name = name
            taken.add(name)
            named += 1
    return named


def _cast_to(node: onnx.NodeProto) -> int | None:
    """The element type a Cast node casts to (None for other nodes)."""
    if node.op_type != "Cast":
        return None
    return next(attr.i for attr in node.attribute if attr.name == "to")


def drop_fp16_round_trips(model: onnx.ModelProto) -> int:
    """Make each FP32 → FP16 → FP32 pair of Casts the converter left read the FP32 tensor directly, in place;
    returns how many pairs.

    The converter casts each output of a node it keeps FP32 to FP16 and each FP16 input of such a node back,
    so a tensor between two FP32 nodes (or from a kept-FP32 node to a graph output) still passes through
    FP16, and a value beyond 65504 becomes ±∞ on the way. A Cast writing a graph output becomes an Identity.
    """
    graph = model.graph
    types = _elem_types(model)
    producers = {name: node for node in graph.node for name in node.output}
    source: dict[str, str] = {}  # the FP32 output of a round trip → the FP32 tensor it started from
    for node in graph.node:
        first = producers.get(node.input[0]) if _cast_to(node) == TensorProto.FLOAT else None
        if (first is not None and _cast_to(first) == TensorProto.FLOAT16
                and types.get(first.input[0]) == TensorProto.FLOAT):
            source[node.output[0]] = first.input[0]

    def start(name: str) -> str:
        while name in source:
            name = source[name]
        return name

    outputs = {value.name for value in graph.output}
    for node in graph.node:
        if node.output and node.output[0] in source and node.output[0] in outputs:
            node.op_type, node.input[0] = "Identity", start(node.output[0])
            del node.attribute[:]
            continue
        for i, name in enumerate(node.input):
            if name in source:
                node.input[i] = start(name)
    # Drop the Casts nobody reads now (the second of each pair, and the first where only it read its output).
    while True:
        read = {name for node in graph.node for name in node.input} | outputs
        kept = [node for node in graph.node if node.op_type != "Cast" or read & set(node.output)]
        if len(kept) == len(graph.node):
            break
        del graph.node[:]
        graph.node.extend(kept)
    present = {name for node in graph.node for name in [*node.input, *node.output]}
    kept_info = [value for value in graph.value_info if value.name in present]
    del graph.value_info[:]
    graph.value_info.extend(kept_info)
    return len(source)


def sort_topologically(graph: onnx.GraphProto) -> None:
    """Order the nodes so each follows the producers of its inputs, otherwise keeping their order, in place.

    ONNX Runtime's FP16 converter appends the Casts it inserts (after the graph inputs, around FP32 nodes)
    at the end, which ``onnx.checker`` refuses ("Nodes in a graph must be topologically sorted")."""
    nodes = list(graph.node)
    producer = {name: index for index, node in enumerate(nodes) for name in node.output if name}
    waiting = [{producer[name] for name in node.input if name in producer} - {index}
               for index, node in enumerate(nodes)]
    readers: defaultdict[int, list[int]] = defaultdict(list)
    for index, needs in enumerate(waiting):
        for need in needs:
            readers[need].append(index)
    ready = [index for index, needs in enumerate(waiting) if not needs]
    heapq.heapify(ready)  # the earliest ready node first: the original order wherever it was valid
    order = []
    while ready:
        index = heapq.heappop(ready)
        order.append(index)
        for reader in readers[index]:
            waiting[reader].discard(index)
            if not waiting[reader]:
                heapq.heappush(ready, reader)
    if len(order) != len(nodes):
        raise ValueError(f"graph {graph.name!r}: its nodes form a cycle")
    del graph.node[:]
    graph.node.extend(nodes[index] for index in order)


def check_fp16_storage(source: onnx.ModelProto, converted: onnx.ModelProto, ranges: dict[str, Fp16Range],
                       what: str = "") -> tuple[str, float]:
    """Every tensor ``converted`` holds in float16 can hold its FP32 values (``ranges`` of ``source``):
    FP16RangeError naming the node that writes it and why, else (the tensor, its largest |x|) of the
    largest FP16 one. ``what`` names the network in the message.

    A tensor of the converted graph holds the values of an FP32 one: a node kept from ``source`` writes
    that node's output; a Cast the converter added, its input's values."""
    original = {node.name: node for node in source.graph.node}
    divisors = _divisors(source.graph)
    producers = {name: node for node in converted.graph.node for name in node.output}

    def fp32_tensor(name: str) -> tuple[str, str]:
        """The FP32 tensor whose values ``name`` holds, and the node of ``source`` writing it ("" for none)."""
        node = producers.get(name)
        while node is not None and node.op_type == "Cast" and node.name not in original:
            name, node = node.input[0], producers.get(node.input[0])
        if node is None:
            return name, ""  # a graph input or an initializer: the converter keeps their names
        return original[node.name].output[list(node.output).index(name)], node.name

    largest, problems = ("", 0.0), []
    for name, elem_type in _elem_types(converted).items():
        if elem_type != TensorProto.FLOAT16:
            continue
        origin, computed_by = fp32_tensor(name)
        writer = producers[name].name if name in producers else "initializer"
        if computed_by and computed_by != writer:  # a Cast the converter added
            writer += f" (a Cast of what {computed_by} computes)"
        if origin not in ranges:
            problems.append(f"{name} (written by {writer}): no FP32 tensor {origin!r} was measured")
            continue
        why = ranges[origin].trouble(divisors.get(origin))
        if why is not None:
            problems.append(f"node {writer} writes {name} in FP16: {why}")
        elif ranges[origin].largest > largest[1]:
            largest = (name, ranges[origin].largest)
    if problems:
        raise FP16RangeError(f"{what + ': ' if what else ''}FP16 cannot hold what the FP32 graph computes on "
                             "the check frames: " + "; ".join(problems)
                             + " (a node writing or reading such a tensor must stay FP32: export/fp16.py)")
    return largest
