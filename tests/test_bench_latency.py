"""benchmarks/latency.py's arithmetic on constructed timings: the summaries, the single stream's figures, the
networks' FLOPs and shares of the peak, and how the alternating blocks and throughput rounds are put together
(real tiny-model Detectors where frames run; every figure set against a hand-computed value or its definition).
No timing targets."""

import os
import statistics

import pytest

from benchmarks.latency import (
    StreamResult,
    best_peak,
    network_figures,
    peak_warning,
    run_paired,
    run_stream,
    stream_figures,
    summarize,
    tail_note,
)
from benchmarks.peak import PeakResult
from pipeline.detector import Detector


def test_summary_of_skewed_unsorted_samples():
    """numpy's linear interpolation on 10, 20, 30, 40, 100 (given out of order): p90 at rank 3.6, p99 at 3.96."""
    summary = summarize([40.0, 10.0, 100.0, 20.0, 30.0])
    assert summary["mean"] == 40.0 and summary["p50"] == 30.0 and summary["max"] == 100.0 and summary["n"] == 5
    assert summary["p90"] == pytest.approx(76.0) and summary["p99"] == pytest.approx(97.6)


def test_the_tail_note_is_said_while_the_percentile_lies_between_the_two_slowest():
    """numpy's p99 of n samples sits at rank 0.99 (n − 1): 98.01 of 0 … 99 for 100 frames (between the two
    slowest, as the note says), 99 for 101 (the second slowest), 99.99 for 102 (past it). p90: 9 for 11, 9.9 for 12.
    The note was left out from 100 frames on, and the p90's from 10."""
    samples = [float(i) for i in range(100)]
    assert 98.0 < summarize(samples)["p99"] < 99.0
    assert "with 100 frames p99 is an interpolation between the two slowest" in tail_note(100)
    assert tail_note(101) != "" and tail_note(102) == ""
    assert summarize([float(i) for i in range(11)])["p90"] == 9.0 and "p90 between the two slowest" in tail_note(11)
    assert "p90" not in tail_note(12) and "p90 between the two slowest" in tail_note(9)


def test_stream_figures_of_known_timings():
    stream = StreamResult(
        end_to_end=[10.0, 20.0, 30.0, 60.0],  # mean 30, p50 25
        stages={"prepare": [1.0, 1.0, 1.0, 1.0], "depth_net": [4.0, 6.0, 8.0, 10.0], "ray_table": [2.0, 0.0, 0.0, 0.0],
                "pixor": [3.0, 3.0, 3.0, 3.0], "pixor_mirror": [2.0, 2.0, 2.0, 2.0]},
        wall_s=0.2, frames=4, overlapped={"ray_table": [1.0, 0.5, 0.5, 0.5], "voxelize": [3.0, 3.0, 5.0, 5.0]})
    figures = stream_figures(stream)
    assert figures["end_to_end_ms"] == summarize(stream.end_to_end)
    assert set(figures["end_to_end_ms"]) >= {"mean", "p50", "p90", "p99"}  # issue #8's keys
    assert figures["fps"] == pytest.approx(1000 / 30) and figures["fps_wall"] == pytest.approx(4 / 0.2)
    assert set(figures["stages_ms"]) == set(stream.stages)
    assert figures["stages_ms"]["depth_net"] == summarize([4.0, 6.0, 8.0, 10.0])
    assert set(figures["overlapped_ms"]) == {"ray_table", "voxelize"} and figures["overlapped_ms"]["voxelize"]["p50"] == 4.0
    # The networks' means (depth 7, PIXOR 3 and its mirror run 2) are 12 of the 30 ms: 18 between them.
    assert figures["non_network_fraction"] == pytest.approx(18 / 30)
    # The first frame waited 2 ms for work whose table took 1: 1 ms, a quarter over the four frames.
    assert figures["ray_tables_on_path_ms"] == pytest.approx(0.25)
    assert figures["non_network_fraction_fixed_calibration"] == pytest.approx((18 - 0.25) / (30 - 0.25))


def test_the_best_peak_reading_of_each_kind_counts_and_readings_apart_are_flagged():
    peak = best_peak([PeakResult(matmul_gflops=100.0, conv_gflops=80.0, threads=2),
                      PeakResult(matmul_gflops=90.0, conv_gflops=120.0, threads=2)])
    assert (peak.matmul_gflops, peak.conv_gflops, peak.threads, peak.peak_gflops) == (100.0, 120.0, 2, 120.0)
    agree = [PeakResult(100.0, 10.0, 1), PeakResult(80.0, 10.0, 1)]  # the lower exactly 0.8 of the higher
    assert peak_warning(agree, 4096) is None
    apart = [PeakResult(100.0, 10.0, 1), PeakResult(79.0, 10.0, 1)]
    assert "(100 and 79 GFLOP/s)" in peak_warning(apart, 4096)
    assert peak_warning(apart, 2048) is None  # a small MatMul's readings vary by themselves


def test_network_figures_count_each_run_and_set_the_p50_against_the_peak():
    stages = {"depth_net": {"p50": 20.0, "mean": 25.0}, "pixor": {"p50": 4.0, "mean": 5.0},
              "pixor_mirror": {"p50": 6.0, "mean": 7.0}}
    peak = PeakResult(matmul_gflops=200.0, conv_gflops=250.0, threads=2)
    # PIXOR with the mirror: 2 runs of 1 GFLOP (1.2 on the graph that runs) in 4 + 6 ms = 200 GFLOP/s.
    pixor = network_figures(stages, ("pixor", "pixor_mirror"), 1e9, 1.2e9, peak)
    assert pixor["runs"] == 2 and pixor["gflops"] == 2.0 and pixor["graph_gflops"] == pytest.approx(2.4)
    assert pixor["ms"] == 10.0 and pixor["achieved_gflops_per_s"] == pytest.approx(200.0)
    assert pixor["peak_fraction"] == pytest.approx(0.8) and pixor["matmul_peak_fraction"] == pytest.approx(1.0)
    depth = network_figures(stages, ("depth_net",), 5e9, 5e9, peak)
    assert (depth["runs"], depth["gflops"], depth["ms"]) == (1, 5.0, 20.0)
    assert depth["peak_fraction"] == pytest.approx(1.0) and depth["matmul_peak_fraction"] == pytest.approx(1.25)
    once = network_figures({"pixor": {"p50": 4.0}}, ("pixor", "pixor_mirror"), 1e9, 1e9, peak)
    assert once["runs"] == 1 and once["ms"] == 4.0 and once["achieved_gflops_per_s"] == pytest.approx(250.0)
    other_provider = network_figures(stages, ("depth_net",), 5e9, 5e9, None)
    assert other_provider["peak_fraction"] is None and other_provider["matmul_peak_fraction"] is None
    assert {"gflops", "ms", "peak_fraction"} <= set(pixor)  # issue #8's keys


class Recording(Detector):
    """The real Detector, each detect call logged in ``calls`` with its label and end-to-end time."""

    def __init__(self, *args, label: str, calls: list[tuple[str, float]], **kwargs):
        super().__init__(*args, **kwargs)
        self.label, self.calls = label, calls

    def detect(self, image, points, calib, score_threshold=None, *args, **kwargs):
        result = super().detect(image, points, calib, score_threshold, *args, **kwargs)
        self.calls.append((self.label, result.timings_ms["total"]))
        return result


@pytest.fixture
def frames():
    from benchmarks.latency import load_frames
    from tests.conftest import KITTI

    return load_frames(KITTI, 2, 16)


def test_the_stream_times_count_frames_after_warmup_ones(tiny_models, frames):
    calls = []
    stream = run_stream(Recording(tiny_models, label="a", calls=calls), frames, 3, 2)
    assert len(calls) == 5 and stream.frames == 3
    assert stream.end_to_end == [ms for _, ms in calls[2:]]
    assert all(len(ms) == 3 for ms in stream.stages.values()) and "total" not in stream.stages


def test_paired_blocks_alternate_each_after_an_untimed_frame_and_give_second_over_first(tiny_models, frames):
    """5 frames in blocks of 2: A B, B A, A B; each block starts with one untimed frame, the last block holds the
    fifth frame, and each block's ratio is the second detector's time over the first's."""
    calls = []
    first, second = Recording(tiny_models, label="a", calls=calls), Recording(tiny_models, label="b", calls=calls)
    one, two, ratios = run_paired(first, second, frames, 5, 1, block=2)
    assert [label for label, _ in calls[:2]] == ["a", "b"]  # one warm-up frame each
    timed, block_sums, position = {"a": [], "b": []}, [], 2
    for order, size in ((("a", "b"), 2), (("b", "a"), 2), (("a", "b"), 1)):
        sums = {}
        for side in order:  # an untimed frame, then the block's timed ones
            run = calls[position: position + size + 1]
            assert [label for label, _ in run] == [side] * (size + 1)
            timed[side] += [ms for _, ms in run[1:]]
            sums[side] = sum(ms for _, ms in run[1:])
            position += size + 1
        block_sums.append(sums)
    assert position == len(calls)
    assert one.end_to_end == timed["a"] and two.end_to_end == timed["b"] and one.frames == two.frames == 5
    assert ratios == pytest.approx([s["b"] / s["a"] for s in block_sums], rel=1e-12)


def test_throughput_figures_are_the_rounds_medians_and_each_runs_frames_over_its_wall_time(tiny_models, frames):
    from benchmarks.latency import run_throughput

    cores = sorted(os.sched_getaffinity(0))[:2]  # the project's machines have two; one core is refused by name
    report = run_throughput(tiny_models, None, None, frames, 2, per_worker=2, warmup=0, cores=cores, rounds=3)
    runs = report["runs"]
    one = [run["fps"] for run in runs if run["workers"] == 1]
    many = [run["fps"] for run in runs if run["workers"] == 2]
    assert len(one) == len(many) == 3
    assert report["fps"] == statistics.median(many) and report["fps_one_worker"] == statistics.median(one)
    assert report["scaling"] == report["fps"] / report["fps_one_worker"]
    by_round = {(run["round"], run["workers"]): run["fps"] for run in runs}
    assert report["scaling_per_round"] == [by_round[r, 2] / by_round[r, 1] for r in range(3)]
    for run in runs:  # fps is every worker's frames over the run's wall time
        assert run["frames"] == 2 * run["workers"] == sum(u["frames"] for u in run["per_worker"])
        assert run["fps"] == pytest.approx(run["frames"] / run["wall_s"], rel=1e-12)
    assert report["cores_per_worker"] == len(runs[1]["per_worker"][0]["cores"]) == 1
    # One core per thread worker: its CPU time is measured, and so is a frame's with one worker and with two.
    per_frame = {n: statistics.median(1e3 * sum(u["cpu_s"] for u in run["per_worker"]) / run["frames"]
                                      for run in runs if run["workers"] == n) for n in (1, 2)}
    cpu = report["cpu_ms_per_frame"]
    assert (cpu["one_worker"], cpu["all_workers"]) == pytest.approx((per_frame[1], per_frame[2]), rel=1e-12)
    assert cpu["ratio"] == pytest.approx(per_frame[2] / per_frame[1], rel=1e-12) and cpu["one_worker"] > 0
    assert {"workers", "fps", "fps_one_worker", "scaling"} <= set(report)  # issue #8's keys


def test_a_frames_cpu_time_alone_and_together_is_the_median_over_the_runs():
    """Each run's CPU time over its frames (ms), the runs of one worker and of all of them apart, medians;
    None where a worker's CPU time was not measured (a thread of more than one core) or a side has no run."""
    from benchmarks.latency import cpu_per_frame

    def run(workers: int, cpu: list) -> dict:
        return {"workers": workers, "frames": 10 * workers, "per_worker": [{"cpu_s": c} for c in cpu]}

    runs = [run(1, [1.0]), run(2, [1.3, 1.1]), run(2, [1.2, 1.2]), run(1, [1.2]), run(1, [1.1]), run(2, [1.5, 1.3])]
    # one worker: 100, 120, 110 ms a frame; two: 120, 120, 140
    assert cpu_per_frame(runs) == pytest.approx({"one_worker": 110.0, "all_workers": 120.0, "ratio": 120 / 110})
    assert cpu_per_frame([*runs[:5], run(2, [1.4, None])]) is None
    assert cpu_per_frame([r for r in runs if r["workers"] == 1]) is None
