"""benchmarks/load.py's summary of a run, on constructed samples: every figure set against a hand-computed value
(numpy's percentiles are linear interpolations between the sorted samples). No service, no timing."""

import math

import pytest

from benchmarks.load import RequestSource, RunContext, Sample, Schedule, memory_trend, per_window, summarise


def context(**overrides) -> RunContext:
    """A closed-loop run of 2 clients on a server started elsewhere, scans thinned by the server."""
    fields = {"url": "http://127.0.0.1:1", "clients": 2, "server": {"preset": "tiny"},
              "thinning": {"where": "server", "beams": 16}, "started_here": False, "client_cpu_s": 1.5}
    return RunContext(**{**fields, **overrides})


def mixed_run() -> list[Sample]:
    """Seven well-formed requests (three 200s, a 503, a 500, a broken connection, a 408) and three broken ones."""
    return [
        Sample(0.0, 100.0, "200", "000000", timings_ms={"total": 90.0, "pixor": 10.0, "emulate_beams": 2.0},
               points=1000),
        Sample(0.5, 10.0, "422", "points-truncated", broken=True, points=5),
        Sample(1.0, 300.0, "200", "000001", timings_ms={"total": 280.0, "pixor": 30.0}, points=3000, lag_ms=50.0),
        Sample(2.0, 50.0, "503", "000000", points=1000),
        Sample(2.5, 20.0, "503", "image-cut-off", broken=True, points=7),
        Sample(3.0, 200.0, "200", "000003", timings_ms={"total": 190.0, "pixor": 11.0, "emulate_beams": 4.0},
               points=2000, lag_ms=20.0),
        Sample(4.0, 70.0, "500", "000001", points=3000),
        Sample(4.5, 5000.0, "500", "calib-without-P2", broken=True, points=9),
        Sample(5.0, 80.0, "error:ReadTimeout", "000000", points=1000),
        Sample(5.5, 60.0, "408", "000003", points=2000),
    ]


def test_the_summary_counts_rates_and_percentiles_of_a_mixed_run():
    result = summarise(mixed_run(), 6.0, {"ready": 100.0, "warm": 120.0, "end": 121.0}, None, context())
    assert result.requests == 10 and result.duration_s == 6.0
    # Status counts, throughput and latency are the well-formed requests'; the broken ones are counted apart.
    assert result.status_counts == {"200": 3, "408": 1, "500": 1, "503": 1, "error:ReadTimeout": 1}
    assert result.throughput_ok_per_s == 3 / 6 and result.throughput_all_per_s == 10 / 6
    ok = result.latency_ms["200"]  # 100, 200, 300 ms
    assert ok["p50"] == 200.0 and ok["mean"] == 200.0 and ok["max"] == 300.0
    assert ok["p90"] == pytest.approx(280.0) and ok["p99"] == pytest.approx(298.0)
    everything = result.latency_ms["all"]  # 50, 60, 70, 80, 100, 200, 300 ms: not the broken request's 5000
    assert everything["p50"] == 80.0 and everything["max"] == 300.0
    assert everything["mean"] == pytest.approx(860 / 7) and everything["p90"] == pytest.approx(240.0)
    assert result.latency_ms["503"]["p50"] == 50.0
    assert set(result.latency_ms) == {"200", "408", "500", "503", "error:ReadTimeout", "all"}
    # The server's stages of the 200s: medians (pixor 10, 30, 11 → 11; a mean would be 17).
    assert result.stage_p50_ms == {"total": 190.0, "pixor": 11.0, "emulate_beams": 3.0}
    assert result.frames_sent == 3  # 000000, 000001, 000003 among the well-formed
    assert result.thinning["points_sent_mean"] == pytest.approx(13000 / 7)
    assert result.thinning["server_thinned_answers"] == 2 and result.thinning["where"] == "server"
    # Only the broken requests' 4xx count as rightly refused (not the well-formed one's 408).
    assert result.broken == {"sent": 3, "answered_4xx": 1,
                             "statuses": {"points-truncated": {"422": 1}, "image-cut-off": {"503": 1},
                                          "calib-without-P2": {"500": 1}}}
    # 5xx other than 503 and broken connections, well-formed or not: the 500, the broken request's 500, the timeout.
    assert result.server_errors == 3
    assert result.trend["p50_ms_first_tenth"] == 100.0 and result.trend["p50_ms_last_tenth"] == 200.0
    assert result.client_cpu_s == 1.5 and result.client_cpu_cores == pytest.approx(1.5 / 6)
    assert result.mode == "closed-loop" and result.latency_from == "send" and result.open_loop == {}
    assert result.server_machine is None and result.client_shares_server_machine is None


def test_the_open_loop_rates_are_over_the_schedules_window_and_latency_from_the_send_takes_off_the_lag():
    schedule = Schedule(due=12, sent=10, late=3, unsent=2, window_s=2.0)
    result = summarise(mixed_run(), 6.0, {"ready": 1.0, "warm": 1.0, "end": 1.0}, None,
                       context(rate_hz=10.0, schedule=schedule, started_here=True))
    loop = result.open_loop
    assert result.mode == "open-loop" and result.latency_from == "schedule"
    assert loop["achieved_rate_hz"] == 10 / 2.0 and loop["ok_rate_hz"] == 3 / 2.0
    assert (loop["due"], loop["sent"], loop["late_sends"], loop["unsent"]) == (12, 10, 3, 2)
    assert loop["max_in_flight"] == 2 and loop["requested_rate_hz"] == 10.0
    # From the send: 100, 300 − 50, 50, 200 − 20, 70, 80, 60 → p50 of 50, 60, 70, 80, 100, 180, 250 is 80, max 250.
    assert loop["latency_from_send_ms"]["max"] == 250.0 and loop["latency_from_send_ms"]["p50"] == 80.0
    assert loop["send_lag_ms"]["max"] == 50.0
    assert result.server_machine == result.client_machine and result.client_shares_server_machine is True


def test_the_first_and_last_tenth_are_by_start_time_and_windows_count_the_200s_that_started_in_them():
    # 20 answered frames, one every second, latency 10, 20, … 200 ms, gathered in the order they finished
    # (not started); 10 refused ones and a broken request answered 200, which count in no window.
    ok = [Sample(float(i), 10.0 * (i + 1), "200", "000000") for i in range(20)]
    samples = ok[10:] + [Sample(i + 0.5, 1.0, "503", "000000") for i in range(10)] + ok[:10]
    samples.append(Sample(0.1, 9999.0, "200", "query-misspelt", broken=True))
    rss = [(0.5, 100.0), (1.5, 110.0), (2.5, 120.0)]
    windows = per_window(samples, rss, 20.0)
    assert [w["start_s"] for w in windows] == [2.0 * k for k in range(10)] and windows[-1]["end_s"] == 20.0
    assert all(w["ok_per_s"] == 1.0 for w in windows)  # two starts per 2 s window, the one at its end not counted
    assert [w["p50_ms"] for w in windows] == [10.0 * (2 * k + 1.5) for k in range(10)]
    assert windows[0]["rss_mb"] == 105.0 and windows[1]["rss_mb"] == 120.0 and math.isnan(windows[2]["rss_mb"])
    result = summarise(samples, 20.0, {"ready": 1.0, "warm": 1.0, "end": 1.0}, None, context())
    # A tenth of the 20 answered frames: the first two started (10, 20 ms) and the last two (190, 200 ms).
    assert result.trend["p50_ms_first_tenth"] == 15.0 and result.trend["p50_ms_last_tenth"] == 195.0


def test_the_memory_trend_is_fitted_after_the_first_tenth_in_mb_per_hour():
    # 10 kB a second = 36 MB an hour; the first tenth of a 20 s run (a start-up spike at 0.5 s) is left out.
    series = [(0.5, 500.0)] + [(float(t), 100.0 + 0.01 * t) for t in range(2, 21)]
    assert memory_trend(series, 20.0) == pytest.approx(36.0)
    assert memory_trend(series[:10], 20.0) is None  # 9 samples after the first tenth: too few for a slope


def test_the_first_broken_request_is_the_bad_everyth():
    from benchmarks.load import KITTI

    source = RequestSource(KITTI, ["000000", "000001"], {}, total=7, bad_every=3)
    assert [upload.broken for upload in iter(source.take, None)] == [False, False, True, False, False, True, False]


def test_the_load_figures_p50_line_is_the_texts_tenths_of_the_200s_in_black_and_the_histogram_marks_p50_p99():
    """The figure's p50 line was per tenth of the run's time while the printed first and last tenth are tenths of
    the 200s in send order; and in the dots' blue, hiding points among them. 30 answers: the first ten all in the
    first second (10 … 100 ms), twenty more over the next 29 s (200 … 2100 ms). Tenths of the 200s (3 each) give
    20 ms first and 2000 ms last, as the text; tenths of time gave 65 ms first. The histogram marks the 200s' p50
    and p99 as the report computes them."""
    pytest.importorskip("matplotlib")
    import matplotlib.colors as mcolors
    import matplotlib.pyplot as plt

    from benchmarks.load import load_figure

    samples = [Sample(0.1 * i, 10.0 * (i + 1), "200", "000000") for i in range(10)]
    samples += [Sample(1.0 + 1.45 * i, 200.0 + 100.0 * i, "200", "000000") for i in range(20)]
    samples.append(Sample(0.5, 5.0, "422", "points-truncated", broken=True))
    result = summarise(samples, 30.0, {"ready": 1.0, "warm": 1.0, "end": 1.0}, None, context())
    fig = load_figure(samples, result, "test")
    try:
        histogram, timeline = fig.axes[:2]
        (dots,) = [ln for ln in timeline.get_lines() if ln.get_label() == "a 200's latency"]
        (p50,) = [ln for ln in timeline.get_lines() if ln.get_label().startswith("p50 ")]
        assert len(p50.get_ydata()) == 10
        assert p50.get_ydata()[0] == result.trend["p50_ms_first_tenth"] == 20.0
        assert p50.get_ydata()[-1] == result.trend["p50_ms_last_tenth"] == 2000.0
        assert not mcolors.same_color(p50.get_color(), dots.get_color())
        assert p50.get_label() == "p50 of each tenth of the 200s (3 each, in send order)"
        marked = sorted(ln.get_xdata()[0] for ln in histogram.get_lines())
        assert marked == [result.latency_ms["200"]["p50"], result.latency_ms["200"]["p99"]]
        assert [t.get_text() for t in histogram.texts] == [f" 200s' p50 {marked[0]:.0f} ms",
                                                           f" 200s' p99 {marked[1]:.0f} ms"]
    finally:
        plt.close(fig)
