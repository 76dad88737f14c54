"""Session 51's fixes: check_models builds TensorRT's engines where the service keeps them."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from pipeline import check_models
from pipeline.detector import Detector
from tests.test_rollout import WEIGHTS


def test_check_models_hands_its_trt_cache_dir_to_the_models_sessions(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """With --provider tensorrt the check built its engines in MODELS/trt_cache/ and had no flag to say otherwise;
    its error for an unwritable cache named the service's --trt-cache-dir. The check now takes that flag and gives
    it to the Detector, which builds the engines there (no TensorRT here: the CPU run shows the folder reaching
    the real Detector, which the check then runs through every check)."""
    given: list[Any] = []

    class Recording(Detector):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            given.append(kwargs.get("trt_cache_dir"))
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(check_models, "Detector", Recording)
    cache = tmp_path / "trt"
    assert check_models.main(["--models", str(WEIGHTS / "edge-lidar16"), "--provider", "cpu",
                              "--trt-cache-dir", str(cache)]) == 0
    assert given == [cache]
    assert capsys.readouterr().out.splitlines()[-1].startswith("passed: ")
    given.clear()
    assert check_models.main(["--models", str(WEIGHTS / "edge-lidar16"), "--provider", "cpu"]) == 0
    assert given == [None]  # the Detector's default, MODELS/trt_cache, as the service's



def test_latency_names_only_a_misspelt_preset_as_the_preset_flags_fault(monkeypatch: pytest.MonkeyPatch,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """latency.py's main turned any ValueError of a whole run into "error: --preset: …" and exit 2, so a defect
    deep in a run read as a misspelt preset. Only get_preset's refusal says so now, with --models too (the held
    preset's check); another ValueError keeps its traceback."""
    from benchmarks import latency

    for argv in (["--preset", "nonsense"], ["--models", str(WEIGHTS / "edge"), "--preset", "nonsense"]):
        assert latency.main([*argv, "--frames", "1"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: --preset: unknown preset 'nonsense'; choose one of paper, edge, tiny"), err

    def broken(*args: Any, **kwargs: Any) -> None:
        raise ValueError("a defect inside the run")

    monkeypatch.setattr(latency, "run", broken)
    with pytest.raises(ValueError, match="a defect inside the run"):
        latency.main(["--models", str(WEIGHTS / "edge"), "--frames", "1"])


def test_the_load_pictures_latency_axis_is_labelled_when_every_latency_lies_within_one_decade() -> None:
    """The histogram's log axis labelled powers of ten only, the other labels blanked: a run whose latencies
    all fell between 157 and 400 ms (a 15 s run of the edge model here) had an x axis without a number."""
    from benchmarks.load import Sample, load_figure, summarise
    from tests.test_bench_load import context

    samples = [Sample(0.5 * i, latency, "200", "000000", timings_ms={"total": latency - 5.0})
               for i, latency in enumerate([157.0, 181.0, 205.0, 236.0, 260.0, 300.0, 340.0, 380.0])]
    result = summarise(samples, 4.0, {"ready": 400.0, "warm": 410.0, "end": 411.0}, None, context())
    figure = load_figure(samples, result, "a run within one decade")
    figure.canvas.draw()
    histogram = figure.axes[0]
    low, high = histogram.get_xlim()
    shown = [(tick.get_loc(), tick.label1.get_text()) for tick in histogram.xaxis.get_major_ticks()
             if low <= tick.get_loc() <= high and tick.label1.get_text()]
    assert [text for _, text in shown] == ["200", "300"], shown


def test_latency_refuses_checkpoints_that_do_not_fit_in_one_line(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """--checkpoints of another preset's run (or a folder without checkpoints) ended in a traceback of the
    exporter's ValueError (FileNotFoundError) once main stopped reading every ValueError as the --preset flag's
    fault; before that the first said "--preset", not the flag at fault. Both are one --checkpoints line now, exit
    2, as python -m export says them."""
    from benchmarks import latency
    from models import build_pixor
    from models.checkpoint import save_checkpoint
    from pipeline.presets import get_preset

    tiny = get_preset("tiny")
    save_checkpoint(tmp_path / "tiny_run" / "pixor.pt", tiny, {"pixor": build_pixor(tiny)}, {"epochs": 1})
    (tmp_path / "empty_run").mkdir()
    for run, says in (("tiny_run", "trained with preset 'tiny'"), ("empty_run", "")):
        assert latency.main(["--checkpoints", str(tmp_path / run), "--frames", "1", "--warmup", "1"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: --checkpoints") and err.count("\n") == 1 and says in err, err


@pytest.mark.parametrize("columns", ["60", "80"])
def test_help_lines_break_at_spaces_only_so_a_flag_is_never_cut_in_two(columns: str,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """argparse's wrapping also broke lines after a hyphen: depth_bound.py's help at 80 columns showed
    "--pixor-" at a line's end and "checkpoint" on the next (models.train and check_models at other widths),
    and a copied command failed. Every flag of every command now stands whole in its --help, and no line
    ends in a word cut at its hyphen."""
    import re

    from pipeline.cli import shown_spellings
    from tests.test_commands import FAMILY, _parser

    monkeypatch.setenv("COLUMNS", columns)
    for name in FAMILY:
        parser = _parser(name, monkeypatch)
        text = parser.format_help()
        cut = [line for line in text.splitlines() if re.search(r"[A-Za-z]-$", line)]  # "16- and 64-line" is prose
        assert not cut, (name, cut)
        for action in parser._actions:  # the spellings --help shows (old ones are hidden aliases)
            assert all(re.search(rf"(?<![\w-]){re.escape(flag)}(?![\w-])", text)
                       for flag in shown_spellings(action)), (name, action.option_strings)


@pytest.mark.parametrize(("model", "thinned_to"), [("edge-lidar64", []), ("edge-lidar16", [16])])
def test_op_profile_thins_scans_for_the_models_own_line_count(model: str, thinned_to: list[int],
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """op_profile thinned every scan to 16 lines by default, "as benchmarks/latency.py", whose default is the
    model's own line count: a 64-line model was profiled on a 16-line scan without a word. Now as latency.py."""
    from benchmarks.op_profile import main
    from pipeline import beams

    calls: list[int] = []
    real = beams.emulate_beams

    def recording(points: Any, lines: int, *args: Any, **kwargs: Any) -> Any:
        calls.append(lines)
        return real(points, lines, *args, **kwargs)

    monkeypatch.setattr(beams, "emulate_beams", recording)
    assert main(["--models", str(WEIGHTS / model), "--frame", "000006", "--runs", "1", "--top", "1"]) == 0
    assert calls == thinned_to


def test_no_command_reads_a_prefix_of_a_flag_as_the_flag(monkeypatch: pytest.MonkeyPatch,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """argparse takes any unambiguous prefix of a long flag: accuracy.py --frame 000003 evaluated the first three
    frames (--frames 3), cache_pseudo and depth_bound likewise, and accuracy.py --plot FILE made a folder named
    FILE (--plots DIR), each with exit 0. Every command now refuses a flag it does not have."""
    from tests.test_commands import FAMILY, _parser

    assert [name for name in FAMILY if _parser(name, monkeypatch).allow_abbrev] == []
    from benchmarks.accuracy import main

    for flag, value in (("--frame", "000003"), ("--plot", "plot.png")):
        with pytest.raises(SystemExit) as refused:
            main(["--data", "tests/data/kitti/training", "--models", str(WEIGHTS / "edge"), "--input",
                  "lidar16+camera", flag, value])
        assert refused.value.code == 2
        assert f"unrecognized arguments: {flag} {value}" in capsys.readouterr().err


def test_check_models_and_op_profile_take_a_frames_number_as_detect_does(capsys: pytest.CaptureFixture[str]) -> None:
    """pipeline.detect --frame 6 runs 000006; check_models and op_profile looked for velodyne/6.bin and exited 2
    ("cannot read"). They take the number too now, and an id as written still wins."""
    from benchmarks.op_profile import main as op_profile
    from pipeline.frame import numbered_frame
    from tests.conftest import KITTI

    assert check_models.main(["--models", str(WEIGHTS / "edge-lidar16"), "--data", str(KITTI), "--frame", "6"]) == 0
    assert "PASS frame    frame 000006 " in capsys.readouterr().out
    assert op_profile(["--models", str(WEIGHTS / "edge-lidar16"), "--data", str(KITTI), "--frame", "6", "--runs", "1",
                       "--top", "1"]) == 0
    assert "frame 000006" in capsys.readouterr().out
    assert [numbered_frame(KITTI, frame) for frame in ("000006", "6", "06", "7", "x")] == [
        "000006", "000006", "000006", "7", "x"]  # 7: no 000007 here, left for the reader to name


@pytest.mark.parametrize(("argv", "data", "progress"), [
    (["--quick", "--out", "OUT"], Path("OUT/data"), True),
    (["--quick", "--out", "OUT", "--data", "D", "--no-progress"], Path("D"), False),
    (["--out", "OUT"], Path("data/sim"), True),
])
def test_reproduce_quick_keeps_its_frames_in_out_and_bars_can_be_hidden(argv: list[str], data: Path, progress: bool,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """--quick, "a smoke test into OUT only", simulated its frames into the checkout's data/sim beside the real
    data sets; and the recipe drew its progress bars into its log with no --no-progress to hide them, as
    models.train and python -m simulation have. The run itself is stood in for: its config is what is checked."""
    from models import reproduce

    seen: list[Any] = []

    def stand_in(config: Any) -> None:
        seen.append(config)
        raise KeyboardInterrupt

    monkeypatch.setattr(reproduce, "run", stand_in)
    assert reproduce.main(argv) == 130
    assert (seen[0].data, seen[0].progress) == (data, progress)


def test_bootstrap_names_an_empty_list_of_detection_sets_and_frame_ids_given_as_one_string() -> None:
    """Found while refactoring bootstrap: no detection set ended in NumPy's "need at least one array to stack",
    and frame_ids="abcde" (a str is a sequence of strs) in a broadcasting error; each names its argument now."""
    from evaluation.kitti_eval import bootstrap
    from tests.test_eval_intervals import frames, obj

    with pytest.raises(ValueError, match="^detection_sets: none given"):
        bootstrap(frames([obj()]), [], resamples=1)
    with pytest.raises(TypeError, match="^frame_ids: one id per frame, not the string 'a'"):
        bootstrap(frames([obj()]), [frames([obj(score=0.9)])], resamples=1, frame_ids="a")


def test_a_result_file_interrupted_mid_write_is_not_left_empty_or_cut(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """write_labels wrote the result in place: Ctrl-C between opening and writing (seen by a reviewer, 1 in 6
    tries of interrupting pipeline.detect as its first result appeared) left an empty data/000000.txt, read as
    "no cars", while detect said it had written nothing; over an earlier run's file it cut that file. The file
    is now written beside it and renamed over it: an interrupted write leaves the earlier file whole and no
    partial file."""
    from pipeline.kitti import read_labels, write_labels
    from tests.conftest import KITTI

    objects = read_labels(KITTI / "label_2" / "000006.txt")
    result = tmp_path / "000006.txt"
    write_labels(result, objects)
    earlier = result.read_bytes()
    real_write_bytes = Path.write_bytes

    def interrupted_write(self: Path, *args: Any, **kwargs: Any) -> int:
        self.open("w").close()  # opened (emptied), then Ctrl-C before a byte is written
        raise KeyboardInterrupt

    monkeypatch.setattr(Path, "write_bytes", interrupted_write)
    with pytest.raises(KeyboardInterrupt):
        write_labels(result, objects[:1])
    monkeypatch.setattr(Path, "write_bytes", real_write_bytes)
    assert result.read_bytes() == earlier and sorted(p.name for p in tmp_path.iterdir()) == ["000006.txt"]
    write_labels(result, objects[:1])
    assert len(result.read_text().splitlines()) == 1
