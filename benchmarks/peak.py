"""The machine's measured peak for ONNX Runtime fp32: a large MatMul and a 256-channel 3×3 convolution.

    python benchmarks/peak.py [--threads N] [--repeats K]

benchmarks/latency.py measures it in the same run as the networks (the networks' share of the peak);
alone, it tells what a CPU can do before any model is timed on it.

Both graphs are built in memory with onnx.helper and timed with the same
session options as the detector, so "fraction of peak" compares like with like.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper, numpy_helper

# Run as a script (python benchmarks/X.py) its own folder is on sys.path, not the repository: put it there
# before the repository's packages are imported, as benchmarks/latency.py does.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.cli import quiet_interrupt
from pipeline.detector import session_options


@dataclass(frozen=True)
class PeakResult:
    """GFLOP/s of each micro-benchmark (median of the timed runs) and the better of the two."""

    matmul_gflops: float
    conv_gflops: float
    threads: int

    @property
    def peak_gflops(self) -> float:
        return max(self.matmul_gflops, self.conv_gflops)


def _session(model: onnx.ModelProto, threads: int) -> ort.InferenceSession:
    """A CPU session of ``model`` with the Detector's own options (pipeline.detector.session_options: full graph
    optimisation, ``threads`` intra-op threads, one inter-op, the pool spinning within a run only)."""
    return ort.InferenceSession(model.SerializeToString(), session_options(threads), providers=["CPUExecutionProvider"])


def _median_seconds(session: ort.InferenceSession, feeds: dict, repeats: int) -> float:
    session.run(None, feeds)
    samples = []
    for _ in range(repeats):
        tic = time.perf_counter()
        session.run(None, feeds)
        samples.append(time.perf_counter() - tic)
    return float(np.median(samples))


def matmul_model(n: int) -> onnx.ModelProto:
    """Y = A · B with B a constant n × n initializer."""
    b = numpy_helper.from_array(np.random.default_rng(0).standard_normal((n, n)).astype(np.float32), "B")
    graph = helper.make_graph(
        [helper.make_node("MatMul", ["A", "B"], ["Y"])], "matmul",
        [helper.make_tensor_value_info("A", TensorProto.FLOAT, [n, n])],
        [helper.make_tensor_value_info("Y", TensorProto.FLOAT, [n, n])], [b],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)


def conv_model(channels: int, size: int) -> onnx.ModelProto:
    """A 3×3 convolution, ``channels`` → ``channels``, padding 1, on a size × size map."""
    w = numpy_helper.from_array(
        (np.random.default_rng(0).standard_normal((channels, channels, 3, 3)) * 0.05).astype(np.float32), "W")
    graph = helper.make_graph(
        [helper.make_node("Conv", ["X", "W"], ["Y"], pads=[1, 1, 1, 1], kernel_shape=[3, 3])], "conv",
        [helper.make_tensor_value_info("X", TensorProto.FLOAT, [1, channels, size, size])],
        [helper.make_tensor_value_info("Y", TensorProto.FLOAT, [1, channels, size, size])], [w],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)


def matmul_flops(n: int) -> int:
    """FLOPs of :func:`matmul_model` (2 × its multiply-accumulates, as export/flops.py counts them)."""
    return 2 * n**3


def conv_flops(channels: int, size: int) -> int:
    """FLOPs of :func:`conv_model` (2 × its multiply-accumulates: 3 × 3 × channels per output, channels × size²
    outputs, the padding keeping the size)."""
    return 2 * channels * channels * 9 * size * size


def measure_peak(threads: int, repeats: int = 5, matmul_n: int = 4096, conv_channels: int = 256,
                 conv_size: int = 96) -> PeakResult:
    """Run both micro-benchmarks with ``threads`` intra-op threads."""
    a = np.random.default_rng(1).standard_normal((matmul_n, matmul_n)).astype(np.float32)
    t = _median_seconds(_session(matmul_model(matmul_n), threads), {"A": a}, repeats)
    matmul = matmul_flops(matmul_n) / t / 1e9
    x = np.random.default_rng(2).standard_normal((1, conv_channels, conv_size, conv_size)).astype(np.float32)
    t = _median_seconds(_session(conv_model(conv_channels, conv_size), threads), {"X": x}, repeats)
    conv = conv_flops(conv_channels, conv_size) / t / 1e9
    return PeakResult(matmul_gflops=matmul, conv_gflops=conv, threads=threads)


@quiet_interrupt("no report was written")
def main(argv: list[str] | None = None) -> int:
    import argparse

    from pipeline.cli import HelpFormatter, examples, positive_int
    from pipeline.cpu import usable_cpus

    parser = argparse.ArgumentParser(allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
                                     prog="python benchmarks/peak.py",
                                     description="Measure ONNX Runtime's fp32 GFLOP/s on this machine: a 4096² MatMul "
                                     "and a 256-channel 3×3 convolution (the peak benchmarks/latency.py divides by).",
                                     epilog=examples("python benchmarks/peak.py --threads 2"),
                                     formatter_class=HelpFormatter)
    parser.add_argument("--threads", type=positive_int, default=usable_cpus(), metavar="N",
                        help="ONNX Runtime's intra-op threads (default: one per usable core, as latency.py's single "
                        "stream; latency.py's --threads are workers)")
    parser.add_argument("--repeats", type=positive_int, default=5, metavar="N",
                        help="timed runs of each; the median counts (default 5)")
    args = parser.parse_args(argv)
    result = measure_peak(args.threads, args.repeats)
    print(f"{args.threads} thread(s): MatMul 4096² {result.matmul_gflops:.0f} GFLOP/s, 3×3 conv 256 channels "
          f"{result.conv_gflops:.0f} GFLOP/s; peak {result.peak_gflops:.0f} GFLOP/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
