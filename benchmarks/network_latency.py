"""Per-network latency: ONNX Runtime vs PyTorch eager, same weights, same real KITTI input.

    python benchmarks/network_latency.py --preset edge --repeats 5

For each preset: export both networks with :func:`export.run` (no parity pass),
then time forward passes of each network, batch 1, fp32, on CPU, alternating
PyTorch eager (``torch.no_grad``, eval mode) and ONNX Runtime (CPU provider,
full graph optimisation) in blocks of ``--block`` runs, after one warm-up run
each. Reports parameters, GFLOP (counted from the ONNX graph), p50 and max
latency.

Why blocks, not run by run: after a run, each runtime's worker threads spin
for a while waiting for more work (PyTorch's OpenMP pool for up to a few
hundred milliseconds), and the other runtime's run right after finds its
cores taken. Run by run, that cost fell on whichever ran second, and on a
small network it was most of the time measured (the tiny preset's ONNX
Runtime runs took longer than PyTorch's). Each block starts with one untimed
run, so every timed run follows one of its own runtime.
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import onnxruntime as ort
from tqdm import tqdm

from export import run as export_run
from export.inputs import kitti_inputs
from pipeline.cli import (
    HelpFormatter,
    add_no_progress,
    examples,
    missing_extra,
    positive_int,
    quiet_interrupt,
    show_progress,
)
from pipeline.cpu import cpu_label, usable_cpus
from pipeline.detector import session_options
from pipeline.errors import TORCH_MISSING
from pipeline.graph_inputs import feeds_for
from pipeline.presets import PRESETS, Preset, get_preset, is_preset_file

try:
    import torch

    from export.exporter import ExportConfig
except ModuleNotFoundError as exc:
    if exc.name != "torch":
        raise
    raise missing_extra(TORCH_MISSING) from exc


@dataclass
class LatencyRow:
    """Latency of one network of one preset (milliseconds)."""

    preset: str  # the preset's name
    network: str
    parameters: int
    gflops: float
    torch_p50_ms: float
    torch_max_ms: float
    ort_p50_ms: float
    ort_max_ms: float
    repeats: int
    threads: int  # intra-op threads of each runtime: read back from the ONNX Runtime session, PyTorch set to it
    preset_file: str | None = None  # the preset file it was read from, as --preset gave it; None: a registered name

    @property
    def speedup(self) -> float:
        return self.torch_p50_ms / self.ort_p50_ms


def _time_alternating(
    first: Callable[[], object], second: Callable[[], object], repeats: int, block: int, bar: tqdm
) -> tuple[list[float], list[float]]:
    """``repeats`` timed calls of each function, in alternating blocks of up to ``block``, in ms.

    Alternating matters on a shared machine: a burst of load from another process then slows
    both runtimes alike instead of skewing one of them. Each block starts with an untimed call
    (the first one also warms the function up), so no timed call follows the other runtime's.
    """
    times: tuple[list[float], list[float]] = ([], [])
    while len(times[1]) < repeats:
        for fn, out in ((first, times[0]), (second, times[1])):
            fn()
            for _ in range(min(block, repeats - len(out))):
                start = time.perf_counter()
                fn()
                out.append((time.perf_counter() - start) * 1e3)
                bar.update(1)
    return times


def export_folder(index: int, preset: Preset) -> str:
    """The folder (one path component) preset number ``index`` is exported into: --preset may be a file's path
    (absolute, or with ``..``), and a preset's name any text, neither of which may lead out of the scratch folder."""
    return f"{index}-{re.sub(r'[^A-Za-z0-9_.-]', '_', preset.name)}"


def measure_preset(preset_name: str, repeats: int, block: int, workdir: Path, bar: tqdm,
                   threads: int | None = None, index: int = 0) -> list[LatencyRow]:
    """Export ``preset_name`` (a name or a preset file) into a folder of its own in ``workdir`` (:func:`export_folder`)
    and time both networks, ONNX Runtime with ``threads`` intra-op threads (None: PyTorch's count, so both
    runtimes have the same cores)."""
    threads = threads or torch.get_num_threads()
    preset = get_preset(preset_name)
    result = export_run(ExportConfig(preset=preset_name, out=workdir / export_folder(index, preset), parity=False))
    inputs = kitti_inputs(preset)
    rows = []
    for network in ("depth", "pixor"):
        module = result.networks[network]
        feeds = inputs.feeds(network)
        tensors = [torch.from_numpy(v) for v in feeds.values()]
        # The Detector's options: ORT's pool spins within a run and stops when it ends, so it does not
        # steal the cores from the PyTorch block after it.
        # With as many threads as PyTorch's: left to ONNX Runtime's default (one per physical core), --threads 1
        # timed one PyTorch thread against every core.
        session = ort.InferenceSession(str(result.files[network]), session_options(threads),
                                       providers=["CPUExecutionProvider"])

        def eager(module: torch.nn.Module = module, tensors: list[torch.Tensor] = tensors) -> object:
            with torch.no_grad():
                return module(*tensors)

        session_inputs = feeds_for(session, feeds)
        bar.set_description(f"{preset.name} {network}")
        torch_ms, ort_ms = _time_alternating(
            eager, lambda session=session, feeds=session_inputs: session.run(None, feeds), repeats, block, bar
        )
        entry = result.manifest["networks"][network]
        rows.append(
            LatencyRow(
                preset=preset.name,
                network=network,
                parameters=entry["parameters"],
                gflops=entry["flops"] / 1e9,
                torch_p50_ms=statistics.median(torch_ms),
                torch_max_ms=max(torch_ms),
                ort_p50_ms=statistics.median(ort_ms),
                ort_max_ms=max(ort_ms),
                repeats=repeats,
                threads=session.get_session_options().intra_op_num_threads,
                preset_file=preset_name if is_preset_file(preset_name) else None,
            )
        )
    return rows


def run(presets: list[str], repeats: int = 5, threads: int | None = None, progress: bool = True,
        block: int = 5) -> list[LatencyRow]:
    """Measure every preset in ``presets``; returns one row per (preset, network). threads: both runtimes'
    intra-op threads (None: one per usable core)."""
    threads = threads or usable_cpus()
    torch.set_num_threads(threads)
    rows: list[LatencyRow] = []
    with tempfile.TemporaryDirectory(prefix="lowres3d-latency-") as tmp, tqdm(
        total=len(presets) * 2 * 2 * repeats, disable=not progress, unit="run"
    ) as bar:
        for index, name in enumerate(presets):
            rows.extend(measure_preset(name, repeats, block, Path(tmp), bar, threads, index))
    return rows


def hardware() -> str:
    """CPU model, generation and the CPUs this process may use (its affinity and quota), for the table header."""
    return f"{cpu_label()}, {usable_cpus()} usable CPUs of {os.cpu_count()}"


def format_table(rows: list[LatencyRow]) -> str:
    """Markdown table of the rows: a preset by its name, and the file it was read from."""
    lines = [
        "| preset | network | params | GFLOP | PyTorch eager p50 (max) ms | ONNX Runtime p50 (max) ms | speed-up |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        preset = f"{r.preset} ({r.preset_file})" if r.preset_file else r.preset
        lines.append(
            f"| {preset} | {r.network} | {r.parameters / 1e6:.2f} M | {r.gflops:.2f} | "
            f"{r.torch_p50_ms:.1f} ({r.torch_max_ms:.1f}) | {r.ort_p50_ms:.1f} ({r.ort_max_ms:.1f}) | {r.speedup:.2f}× |"
        )
    return "\n".join(lines)


def _preset_name(text: str) -> str:
    """A preset name get_preset knows (argparse shows the ValueError's message); a preset file is checked after
    parsing (:func:`main`), its faults said in one line."""
    if is_preset_file(text):
        return text
    try:
        get_preset(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


@quiet_interrupt("no report was written")
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
        prog="python benchmarks/network_latency.py",
        description="Per-network latency, ONNX Runtime vs PyTorch eager (fp32, CPU, batch 1, same weights and input).",
        epilog=examples("python benchmarks/network_latency.py --preset edge --preset paper --repeats 5"),
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--preset", action="append", type=_preset_name, metavar="P",
                        help=f"preset to measure, with suffixes as everywhere (edge-split-near35) (repeatable; "
                        f"default: {', '.join(sorted(PRESETS))})")
    parser.add_argument("--repeats", type=positive_int, default=5, metavar="N",
                        help="timed runs per network and runtime, after 1 warm-up (default 5)")
    parser.add_argument("--block", type=positive_int, default=5, metavar="N",
                        help="runs of one runtime before switching to the other (default 5); each block starts "
                             "with one untimed run")
    parser.add_argument("--threads", type=positive_int, default=None, metavar="N",
                        help="intra-op threads of both runtimes (default: one per usable core)")
    add_no_progress(parser)
    args = parser.parse_args(argv)
    presets = args.preset or list(PRESETS)
    for text in filter(is_preset_file, presets):
        try:
            get_preset(text)
        except ValueError as exc:  # the file's fault, in one line: argparse's usage says nothing of it
            print(f"error: argument --preset: {exc}", file=sys.stderr)
            return 2
    rows = run(presets, args.repeats, args.threads, progress=show_progress(args.no_progress), block=args.block)
    print(
        f"{hardware()}; fp32, batch 1, CPUExecutionProvider (onnxruntime {ort.__version__}) and torch "
        f"{torch.__version__}, each with {torch.get_num_threads()} intra-op threads; {args.repeats} runs after 1 warm-up, "
        f"alternating in blocks of {args.block}; input: KITTI 000006"
    )
    print(format_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
