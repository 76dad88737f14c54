"""Where a network's time goes, operator by operator: ONNX Runtime's own profiler on the graph it runs.

    python benchmarks/latency.py --models DIR --ops

A network's share of the machine's peak (benchmarks/latency.py) says how far it is from the hardware,
not why. This times every kernel of the graph ONNX Runtime actually runs (after its fusions and
layout rewrites: ``QLinearConv`` in NHWC, the ``Transpose`` and ``ReorderInput`` nodes it inserts
around them), with the Detector's session options and thread count, on the inputs a real frame
gives the network. It then splits the time between the convolutions (and MatMuls), whose FLOPs the
manifest counts, and everything else, so a reader sees whether the kernels or the glue between them
fall short: on this project's Zen 5 machine the edge INT8 networks spent 6–30 % of their time in layout
Transposes with two threads (docs/measurements.md, session 25).
"""

from __future__ import annotations

import json
import tempfile
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import onnxruntime as ort

from pipeline.detector import session_options
from pipeline.graph_inputs import feeds_for

# Operators whose multiply–accumulates export/flops.py counts, as the profiler names their kernels.
COMPUTE_SUFFIXES = ("Conv", "ConvTranspose", "MatMul", "Gemm", "MatMulInteger")
PROFILED_PROVIDERS = ("CPUExecutionProvider", "CUDAExecutionProvider")


@dataclass
class OpProfile:
    """Median time per run of each operator type over the profiled runs (milliseconds)."""

    by_op: dict[str, float] = field(default_factory=dict)
    nodes: dict[str, int] = field(default_factory=dict)  # kernels of each type in the optimised graph
    runs: int = 0
    run_ms: float = 0.0  # median wall time of a profiled run (the profiler adds a little to each kernel)

    @property
    def kernels_ms(self) -> float:
        return sum(self.by_op.values())

    @property
    def compute_ms(self) -> float:
        """Time in the kernels whose FLOPs are counted (convolutions, MatMuls)."""
        return sum(ms for op, ms in self.by_op.items() if is_compute(op))

    def to_dict(self, gflops: float, matmul_gflops: float) -> dict:
        """The JSON form, with the counted convolutions' own rate against the MatMul peak."""
        total = self.kernels_ms
        rate = gflops / (self.compute_ms / 1e3) if self.compute_ms > 0 else 0.0
        return {"profiled_runs": self.runs, "run_ms": self.run_ms, "kernels_ms": total, "compute_ms": self.compute_ms,
                "compute_gflops_per_s": rate, "compute_matmul_peak_fraction": rate / matmul_gflops if matmul_gflops else 0.0,
                "by_op": {op: {"ms": ms, "share": ms / total if total else 0.0, "nodes": self.nodes[op]}
                          for op, ms in sorted(self.by_op.items(), key=lambda item: -item[1])}}


def is_compute(op: str) -> bool:
    """Whether the profiler's operator name is one whose FLOPs export/flops.py counts (Conv, QLinearConv, …)."""
    return op.endswith(COMPUTE_SUFFIXES)


def kernel_times(events: list[dict]) -> tuple[dict[str, list[float]], dict[str, str]]:
    """Per node, its kernel times in microseconds (one per run, in order), and its operator type."""
    times: dict[str, list[float]] = defaultdict(list)
    ops: dict[str, str] = {}
    for event in events:
        name = event.get("name", "")
        if event.get("cat") == "Node" and name.endswith("_kernel_time"):
            node = name[: -len("_kernel_time")]
            times[node].append(float(event["dur"]))
            ops[node] = event["args"]["op_name"]
    return times, ops


def summarize_events(events: list[dict], runs: int) -> OpProfile:
    """:class:`OpProfile` of the last ``runs`` runs in a profile: per node the median over them, summed per type."""
    times, ops = kernel_times(events)
    walls = [float(e["dur"]) for e in events if e.get("cat") == "Session" and e.get("name") == "model_run"]
    profile = OpProfile(runs=runs, run_ms=float(np.median(walls[-runs:])) / 1e3 if walls else 0.0)
    for node, samples in times.items():
        op = ops[node]
        profile.by_op[op] = profile.by_op.get(op, 0.0) + float(np.median(samples[-runs:])) / 1e3
        profile.nodes[op] = profile.nodes.get(op, 0) + 1
    return profile


def profile_network(model: Path, providers: list[str], threads: int, feeds: dict[str, np.ndarray],
                    runs: int = 20, warmup: int = 3) -> OpProfile:
    """Profile ``runs`` runs of one network (after ``warmup`` runs) in a session like the Detector's."""
    if providers[0] not in PROFILED_PROVIDERS:
        raise ValueError(f"{providers[0]} runs the graph as its own engine; ONNX Runtime's profiler times "
                         f"operators on {' and '.join(PROFILED_PROVIDERS)} only")
    with tempfile.TemporaryDirectory(prefix="lowres3d-ops-") as scratch:
        options = session_options(threads)
        options.enable_profiling = True
        options.profile_file_prefix = str(Path(scratch) / "profile")
        session = ort.InferenceSession(str(model), options, providers=providers)
        feeds = feeds_for(session, feeds)
        for _ in range(warmup + runs):
            session.run(None, feeds)
        events = json.loads(Path(session.end_profiling()).read_text())
    return summarize_events(events, runs)


def describe(name: str, profile: dict, shown: int = 6) -> str:
    """One line per network: the largest operator types and the convolutions' own rate."""
    parts = [f"{op} {entry['ms']:.2f} ms ({100 * entry['share']:.0f} %)"
             for op, entry in list(profile["by_op"].items())[:shown]]
    rest = sum(entry["ms"] for entry in list(profile["by_op"].values())[shown:])
    if rest:
        parts.append(f"others {rest:.2f} ms")
    return (f"  {name:6s} operators (median of {profile['profiled_runs']} profiled runs of {profile['run_ms']:.1f} ms, "
            f"{profile['kernels_ms']:.1f} ms in kernels): {', '.join(parts)}; the counted convolutions alone "
            f"{profile['compute_gflops_per_s']:.0f} GFLOP/s ({100 * profile['compute_matmul_peak_fraction']:.0f} % of "
            "the fp32 MatMul's)")
