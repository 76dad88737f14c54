"""Where a network's time goes, operator by operator: ONNX Runtime's own profiler on the graph it runs.

    python benchmarks/latency.py --models DIR --ops        # per operator type, in the latency report
    python benchmarks/op_profile.py --models DIR [--top N]  # per node, on one real frame

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
import sys
import tempfile
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import onnxruntime as ort

# Run as a script (python benchmarks/X.py) its own folder is on sys.path, not the repository: put it there
# before the repository's packages are imported, as benchmarks/latency.py does.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.cli import quiet_interrupt
from pipeline.detector import session_options
from pipeline.graph_inputs import feeds_for

# Operators whose multiply–accumulates export/flops.py counts, as the profiler names their kernels.
COMPUTE_SUFFIXES = ("Conv", "ConvTranspose", "MatMul", "Gemm", "MatMulInteger")
# The CPU alone: on CUDA the profiler's kernel times are those of the launches, not of the GPU's work, which
# runs later (a CUPTI build of ONNX Runtime would be needed); TensorRT runs a graph as an engine of its own.
PROFILED_PROVIDERS = ("CPUExecutionProvider",)
GPU_PROFILER_HINT = "profile a GPU with NVIDIA Nsight Systems (nsys profile python …)"


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
    return summarize_events(profile_events(model, providers, threads, feeds, runs, warmup), runs)


def profile_events(model: Path, providers: list[str], threads: int, feeds: dict[str, np.ndarray],
                   runs: int = 20, warmup: int = 3) -> list[dict]:
    """The profiler's events of ``warmup + runs`` runs of one network in a session like the Detector's."""
    if providers[0] not in PROFILED_PROVIDERS:
        raise ValueError(f"{providers[0]}: ONNX Runtime's profiler times the operators of the CPU provider only (on "
                         f"a GPU its kernel times are the launches'; TensorRT runs an engine of its own); "
                         f"{GPU_PROFILER_HINT}")
    with tempfile.TemporaryDirectory(prefix="lowres3d-ops-") as scratch:
        options = session_options(threads)
        options.enable_profiling = True
        options.profile_file_prefix = str(Path(scratch) / "profile")
        session = ort.InferenceSession(str(model), options, providers=providers)
        feeds = feeds_for(session, feeds)
        for _ in range(warmup + runs):
            session.run(None, feeds)
        return json.loads(Path(session.end_profiling()).read_text())


@dataclass(frozen=True)
class NodeTime:
    """One kernel of the optimised graph: its median time per run, and for a convolution its rate."""

    node: str
    op: str
    ms: float
    output_shape: tuple[int, ...]
    gflops: float  # 0 for operators whose FLOPs are not counted


def _conv_gflop(args: dict) -> float:
    """A fp32 NCHW(c) ``Conv``'s GFLOP from the profiler's shapes: 2 × output elements × weights per output.

    The profiler records the shapes ONNX Runtime ran with; in the blocked layout the channels are padded
    to the block, so this counts what the kernel computes."""
    inputs, outputs = args.get("input_type_shape") or [], args.get("output_type_shape") or []
    if len(inputs) < 2 or not outputs:
        return 0.0
    weight = [int(d) for d in next(iter(inputs[1].values()))]
    output = [int(d) for d in next(iter(outputs[0].values()))]
    if len(weight) != 4 or len(output) != 4:
        return 0.0
    return 2.0 * float(np.prod(output)) * float(np.prod(weight[1:])) / 1e9


def node_times(events: list[dict], runs: int) -> list[NodeTime]:
    """Every kernel's median time over the last ``runs`` runs, slowest first."""
    times, ops = kernel_times(events)
    args = {e["name"][: -len("_kernel_time")]: e.get("args", {}) for e in events
            if e.get("cat") == "Node" and e.get("name", "").endswith("_kernel_time")}
    nodes = []
    for node, samples in times.items():
        shapes = args[node].get("output_type_shape") or [{}]
        output = tuple(int(d) for d in next(iter(shapes[0].values()), []))
        gflop = _conv_gflop(args[node]) if ops[node] == "Conv" else 0.0
        nodes.append(NodeTime(node, ops[node], float(np.median(samples[-runs:])) / 1e3, output, gflop))
    return sorted(nodes, key=lambda n: -n.ms)


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


@quiet_interrupt("no report was written")
def main(argv: list[str] | None = None) -> int:
    """Per-node times of each network of a model directory on one frame, slowest first."""
    import argparse

    from benchmarks.latency import BUNDLED, load_frames
    from pipeline.beams import BEAM_COUNTS, emulate_beams, lines_to_thin_to
    from pipeline.cli import HelpFormatter, examples, positive_int
    from pipeline.detector import Detector
    from pipeline.errors import InputError
    from pipeline.frame import load_frame, numbered_frame
    from pipeline.model_files import DEFAULT_MODELS, ModelFileError

    parser = argparse.ArgumentParser(
        allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
        prog="python benchmarks/op_profile.py",
        description="Time every kernel of a model directory's networks on one real frame with ONNX Runtime's "
        "profiler (the graph it runs, after its fusions and layout changes), slowest first, with each "
        "convolution's GFLOP/s. benchmarks/latency.py --ops gives the totals per operator type.",
        epilog=examples("python benchmarks/op_profile.py --models weights/edge --top 10"),
        formatter_class=HelpFormatter)
    parser.add_argument("--models", type=Path, default=DEFAULT_MODELS, metavar="DIR",
                        help=f"model directory (default {DEFAULT_MODELS})")
    parser.add_argument("--data", type=Path, default=BUNDLED, metavar="DIR",
                        help="KITTI-layout folder (default: the bundled frames)")
    parser.add_argument("--frame", metavar="ID", help="frame id in --data, or its number (6 for 000006; default: "
                        "its first)")
    parser.add_argument("--provider", choices=["cpu"], default="cpu",
                        help="execution provider: the CPU only (on CUDA ONNX Runtime's profiler times the kernels' "
                        f"launches, not the GPU's work, and TensorRT runs an engine of its own; {GPU_PROFILER_HINT})")
    parser.add_argument("--emulate-beams", "--beams", dest="beams", type=int, choices=(0, *BEAM_COUNTS),
                        metavar="N", help="thin the scan to N lines first, 0 to keep it as stored (default: the "
                        "model's own line count, as benchmarks/latency.py: a 64-line model's scan as stored, 16 "
                        "for the others)")  # --beams: its old spelling, kept for scripts (a hidden alias)
    parser.add_argument("--threads", type=positive_int, default=2, metavar="N",
                        help="ONNX Runtime's intra-op threads (default 2; latency.py's --threads are workers)")
    parser.add_argument("--runs", type=positive_int, default=20, metavar="N",
                        help="profiled runs after 3 warm-up runs (default 20)")
    parser.add_argument("--top", type=positive_int, default=15, metavar="N",
                        help="slowest nodes shown per network (default 15)")
    args = parser.parse_args(argv)
    try:
        detector = Detector(args.models, providers=args.provider, intra_op_threads=args.threads)
        if args.beams is None:  # the model's own, as latency.py: a 64-line model's frames were not thinned
            args.beams = lines_to_thin_to(detector.trained_lines)
        if args.frame is None:
            frame = load_frames(args.data, 1, args.beams or None)[0]
        else:
            frame = load_frame(args.data, numbered_frame(args.data, args.frame), with_labels=False)
            if args.beams:
                frame.points = emulate_beams(frame.points, args.beams)
        for name, feeds in detector.network_inputs(frame.image, frame.points, frame.calib).items():
            model = detector.model_dir / detector.manifest["networks"][name]["file"]
            try:
                events = profile_events(model, detector.providers_in_use[name], args.threads, feeds, args.runs)
            except ValueError as exc:
                raise InputError(f"--models: {exc}") from None
            nodes = node_times(events, args.runs)
            total = sum(n.ms for n in nodes)
            print(f"{name} ({model}, frame {frame.frame_id}, {args.threads} thread(s)): {total:.2f} ms in "
                  f"{len(nodes)} kernels; the slowest {min(args.top, len(nodes))} (a Conv's GFLOP/s counts the "
                  "channels as the kernel ran them, padded to ONNX Runtime's block: a 24-channel conv's reads "
                  "up to 1.78× its useful rate):")
            for n in nodes[: args.top]:
                rate = f"{n.gflops / (n.ms / 1e3):6.0f} GFLOP/s" if n.gflops and n.ms else " " * 13
                shape = "×".join(map(str, n.output_shape))
                print(f"  {n.ms:7.2f} ms {100 * n.ms / total:5.1f} %  {n.op:16s} {rate}  out {shape:18s} {n.node}")
    except (InputError, ModelFileError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
