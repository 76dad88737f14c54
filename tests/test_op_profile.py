"""benchmarks/op_profile.py: ONNX Runtime's profiler on a real graph, summed per operator type."""

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from benchmarks.op_profile import is_compute, main, node_times, profile_events, profile_network


def conv_then_transpose(path):
    """A 3×3 convolution (16 → 16 channels, 32 × 32) followed by an NCHW → NHWC Transpose."""
    weight = numpy_helper.from_array(np.random.default_rng(0).standard_normal((16, 16, 3, 3)).astype(np.float32), "w")
    graph = helper.make_graph(
        [helper.make_node("Conv", ["x", "w"], ["y"], pads=[1, 1, 1, 1]),
         helper.make_node("Transpose", ["y"], ["z"], perm=[0, 2, 3, 1])],
        "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 16, 32, 32])],
        [helper.make_tensor_value_info("z", TensorProto.FLOAT, [1, 32, 32, 16])], initializer=[weight])
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), str(path))
    return 2 * 16 * 16 * 9 * 32 * 32  # FLOPs of the convolution


def test_each_kernel_is_timed_and_only_the_counted_ones_give_the_rate(tmp_path):
    flops = conv_then_transpose(tmp_path / "g.onnx")
    feeds = {"x": np.ones((1, 16, 32, 32), np.float32)}
    profile = profile_network(tmp_path / "g.onnx", ["CPUExecutionProvider"], 1, feeds, runs=5, warmup=1)
    assert profile.runs == 5
    compute = [op for op in profile.by_op if is_compute(op)]
    # ONNX Runtime may rewrite the Conv (a blocked-layout Conv between Reorders): one counted kernel either way.
    assert len(compute) == 1 and profile.nodes[compute[0]] == 1
    assert profile.compute_ms == profile.by_op[compute[0]] > 0
    assert profile.kernels_ms > profile.compute_ms  # the layout change is timed, not counted
    assert profile.run_ms >= profile.kernels_ms * 0.9  # a run's wall time holds its kernels (medians: not exactly)
    entry = profile.to_dict(flops / 1e9, matmul_gflops=100.0)
    assert entry["compute_gflops_per_s"] == pytest.approx(flops / 1e9 / (profile.compute_ms / 1e3))
    assert entry["compute_matmul_peak_fraction"] == pytest.approx(entry["compute_gflops_per_s"] / 100.0)
    assert list(entry["by_op"]) == sorted(entry["by_op"], key=lambda op: -entry["by_op"][op]["ms"])


def test_each_node_is_listed_slowest_first_with_the_convolutions_flops(tmp_path):
    flops = conv_then_transpose(tmp_path / "g.onnx")
    events = profile_events(tmp_path / "g.onnx", ["CPUExecutionProvider"], 1,
                            {"x": np.ones((1, 16, 32, 32), np.float32)}, runs=5, warmup=1)
    nodes = node_times(events, 5)
    assert [n.ms for n in nodes] == sorted((n.ms for n in nodes), reverse=True) and all(n.ms > 0 for n in nodes)
    convs = [n for n in nodes if n.op == "Conv"]
    assert len(convs) == 1 and convs[0].gflops == pytest.approx(flops / 1e9)  # 16 channels: no block padding
    # The Transpose to NHWC: as is, or folded into the blocked layout's ReorderOutput.
    assert [n.output_shape for n in nodes if n.op in ("Transpose", "ReorderOutput")] == [(1, 32, 32, 16)]
    assert all(n.gflops == 0 for n in nodes if n.op != "Conv")


def test_the_command_lists_each_networks_slowest_nodes(tiny_models, capsys):
    assert main(["--models", str(tiny_models), "--runs", "2", "--top", "3", "--threads", "1"]) == 0
    out = capsys.readouterr().out.splitlines()
    headers = [i for i, line in enumerate(out) if line.startswith(("depth (", "pixor ("))]
    assert [out[i].split()[0] for i in headers] == ["depth", "pixor"]
    assert all(len([line for line in out[i + 1 : i + 4] if " ms " in line]) == 3 for i in headers)
    assert main(["--models", str(tiny_models.parent / "nowhere")]) == 2 and "error:" in capsys.readouterr().err


def test_the_command_profiles_the_frame_and_provider_asked_for(tiny_models, capsys):
    """--frame as in frame_ops.py (default: the folder's first), --provider as in latency.py."""
    assert main(["--models", str(tiny_models), "--runs", "1", "--top", "1", "--frame", "000004", "--provider", "cpu"]) == 0
    headers = [line for line in capsys.readouterr().out.splitlines() if line.startswith(("depth (", "pixor ("))]
    assert len(headers) == 2 and all("frame 000004," in line for line in headers)
    assert main(["--models", str(tiny_models), "--frame", "999999"]) == 2
    assert "999999" in capsys.readouterr().err


def test_operator_names_counted_as_compute():
    assert all(is_compute(op) for op in ("Conv", "FusedConv", "QLinearConv", "ConvTranspose", "MatMul", "Gemm"))
    assert not any(is_compute(op) for op in ("Transpose", "ReorderInput", "DepthToSpace", "QuantizeLinear"))


def test_a_gpu_provider_is_refused_before_a_session_is_made(tmp_path, capsys):
    """On CUDA the profiler's kernel times are the launches' (the GPU runs them later), and TensorRT runs an
    engine of its own: only the CPU provider is profiled, and the refusal points to nsys."""
    for provider in ("TensorrtExecutionProvider", "CUDAExecutionProvider"):
        with pytest.raises(ValueError, match=f"{provider}: ONNX Runtime's profiler times the operators of the CPU "
                                             "provider only .* Nsight Systems"):
            profile_network(tmp_path / "absent.onnx", [provider, "CPUExecutionProvider"], 1, {})
    with pytest.raises(SystemExit):
        main(["--provider", "cuda"])
    assert "invalid choice: 'cuda'" in capsys.readouterr().err


def test_the_summary_takes_the_median_of_the_last_runs_per_node_summed_per_type():
    """A constructed profile (microseconds, as ONNX Runtime writes it): one warm-up run whose times must not count,
    then three; two Conv nodes and a Transpose."""
    from benchmarks.op_profile import summarize_events

    def kernel(node, op, us):
        return {"cat": "Node", "name": f"{node}_kernel_time", "dur": us, "args": {"op_name": op}}

    runs = [  # conv_a, conv_b, transpose, the whole run
        (9000, 9000, 9000, 50000),  # warm-up
        (1000, 500, 100, 4000), (3000, 500, 300, 6000), (2000, 800, 200, 5000),
    ]
    events = []
    for a, b, t, whole in runs:
        events += [kernel("conv_a", "Conv", a), kernel("conv_b", "Conv", b), kernel("tr", "Transpose", t),
                   {"cat": "Session", "name": "model_run", "dur": whole}]
    profile = summarize_events(events, 3)
    # Medians over the last three runs: conv_a 2 ms, conv_b 0.5 ms, the Transpose 0.2 ms, a run 5 ms.
    assert profile.by_op == pytest.approx({"Conv": 2.5, "Transpose": 0.2}) and profile.nodes == {"Conv": 2, "Transpose": 1}
    assert profile.run_ms == pytest.approx(5.0) and profile.kernels_ms == pytest.approx(2.7)
    assert profile.compute_ms == pytest.approx(2.5)
    entry = profile.to_dict(gflops=0.005, matmul_gflops=4.0)  # 5 MFLOP in the 2.5 ms of the convolutions
    assert entry["compute_gflops_per_s"] == pytest.approx(2.0) and entry["compute_matmul_peak_fraction"] == pytest.approx(0.5)
    assert entry["by_op"]["Conv"]["share"] == pytest.approx(2.5 / 2.7) and entry["by_op"]["Conv"]["nodes"] == 2
