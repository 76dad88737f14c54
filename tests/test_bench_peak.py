"""benchmarks/peak.py's arithmetic: the FLOPs it divides by are those export/flops.py counts on the very graphs it
times, and a reading is the median of the timed runs after an untimed one (a constructed clock; no timing)."""

import numpy as np
import pytest

from benchmarks import peak
from export.flops import count_flops


def test_the_flops_divided_by_are_those_of_the_graphs_timed():
    assert peak.matmul_flops(64) == count_flops(peak.matmul_model(64)).total == 2 * 64**3
    assert peak.conv_flops(8, 12) == count_flops(peak.conv_model(8, 12)).total == 2 * 8 * 8 * 9 * 12 * 12


def test_the_micro_benchmarks_keep_their_sizes():
    """The conv pads by one (its output the size of its input, as conv_flops counts it)."""
    matmul = peak._session(peak.matmul_model(16), 1)
    a = np.ones((16, 16), np.float32)
    assert matmul.run(None, {"A": a})[0].shape == (16, 16)
    conv = peak._session(peak.conv_model(4, 10), 1)
    assert conv.run(None, {"X": np.ones((1, 4, 10, 10), np.float32)})[0].shape == (1, 4, 10, 10)


def test_a_reading_is_the_median_of_the_timed_runs_after_an_untimed_one(monkeypatch):
    class Counting:
        """Stands in for a session: counts its runs, each of which the constructed clock times."""

        runs = 0

        def run(self, outputs, feeds):
            self.runs += 1

    # perf_counter read before and after each timed run: runs of 1, 7 and 2 s, median 2 (mean 3.33, min 1).
    ticks = iter([0.0, 1.0, 10.0, 17.0, 20.0, 22.0])
    monkeypatch.setattr(peak.time, "perf_counter", lambda: next(ticks))
    session = Counting()
    assert peak._median_seconds(session, {}, 3) == 2.0
    assert session.runs == 4  # one untimed


def test_the_peak_is_the_better_micro_benchmark():
    assert peak.PeakResult(matmul_gflops=10.0, conv_gflops=12.5, threads=1).peak_gflops == 12.5
    assert peak.PeakResult(matmul_gflops=30.0, conv_gflops=12.5, threads=1).peak_gflops == 30.0
    with pytest.raises(AttributeError):  # frozen: a reading is not edited after the fact
        peak.PeakResult(1.0, 1.0, 1).matmul_gflops = 2.0
