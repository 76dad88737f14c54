"""Session 51's guards and fixes, mutation-tested: each test here failed on a mutant the existing tests let
through (the audit's table is in its report)."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.errors import InputError
from tests.test_rollout import WEIGHTS


def _load_figure_of(latencies_ms: list[float]):
    """load.py's figure of a run whose requests took ``latencies_ms``, drawn."""
    from benchmarks.load import Sample, load_figure, summarise
    from tests.test_bench_load import context

    samples = [Sample(0.5 * i, latency, "200", "000000", timings_ms={"total": latency - 5.0})
               for i, latency in enumerate(latencies_ms)]
    result = summarise(samples, 4.0, {"ready": 400.0, "warm": 410.0, "end": 411.0}, None, context())
    figure = load_figure(samples, result, "a run")
    figure.canvas.draw()
    return figure


def _labels_in_view(axis, which: str = "major") -> list[str]:
    """The non-empty tick labels of ``axis`` within its view."""
    low, high = axis.get_view_interval()
    ticks = axis.get_major_ticks() if which == "major" else axis.get_minor_ticks()
    return [tick.label1.get_text() for tick in ticks if low <= tick.get_loc() <= high and tick.label1.get_text()]


def test_log_ticks_prefer_powers_of_ten_and_keep_the_ends_of_the_range() -> None:
    """Powers of ten come first (1-2-5 only when fewer than two lie in view), and a power of ten at either end
    of the range is a tick: the last decade and the ends themselves count."""
    from benchmarks.load import log_ticks

    assert log_ticks(10.0, 1000.0) == [10.0, 100.0, 1000.0]
    assert log_ticks(100.0, 1000.0) == [100.0, 1000.0]


@pytest.mark.parametrize(("latencies", "labels"), [([152.0], ["152", "159"]), ([150.0], ["150", "157"]),
                                                   ([1003.0], ["1010", "1050"])])
def test_a_run_with_one_latency_has_two_labels_on_its_latency_axis(latencies: list[float],
                                                                    labels: list[str]) -> None:
    """Latencies too close for any step of 1-2-5 or finer (one request; every request alike) fell back to the
    range's ends at two significant digits, which lay outside the axis (150 and 160 for 152-160 ms): no number
    on it, the fault 72dd71c mended for one decade. The ticks are now round values inside the range."""
    figure = _load_figure_of(latencies)
    assert _labels_in_view(figure.axes[0].xaxis) == labels


def test_the_latency_axis_shows_no_minor_labels_between_its_ticks() -> None:
    """matplotlib labels a log axis' minor ticks when it spans less than a decade: they overlapped the labelled
    ticks (160, 170, … over 200 and 300)."""
    figure = _load_figure_of([157.0, 181.0, 205.0, 236.0, 260.0, 300.0, 340.0, 380.0])
    assert figure.axes[0].xaxis.get_minor_ticks()  # there are minor ticks to leave blank
    assert _labels_in_view(figure.axes[0].xaxis, "minor") == []


def test_an_exporter_refusal_that_names_checkpoints_is_not_given_the_flag_twice() -> None:
    """The exporter's own messages begin with --checkpoints (an empty folder's FileNotFoundError); only the
    others (a checkpoint of another preset's) take the flag in front. Other exceptions are no refusal."""
    from benchmarks.latency import _checkpoints_refused

    for raised, said in ((FileNotFoundError("--checkpoints runs/x: no pixor.pt in it"),
                          "--checkpoints runs/x: no pixor.pt in it"),
                         (ValueError("trained with preset 'tiny'"), "--checkpoints: trained with preset 'tiny'")):
        with pytest.raises(InputError) as refused, _checkpoints_refused():
            raise raised
        assert str(refused.value) == said
    with pytest.raises(KeyError), _checkpoints_refused():
        raise KeyError("a defect, not the flag's")


def test_the_torch_twin_refuses_a_folder_without_checkpoints_in_one_line(tmp_path: Path) -> None:
    """latency.py --compare-torch --models DIR --checkpoints EMPTY: the twin's export refuses in one
    --checkpoints line (InputError), not a FileNotFoundError traceback. Needs torch."""
    from benchmarks.latency import torch_twin
    from pipeline.detector import Detector

    with pytest.raises(InputError, match=r"^--checkpoints "):
        torch_twin(Detector(WEIGHTS / "edge-lidar16", providers="cpu"), tmp_path)


def test_a_frame_id_as_written_wins_and_only_a_number_is_padded(tmp_path: Path) -> None:
    """numbered_frame pads a plain number whose id is not there as written (6 -> 000006); a folder holding both
    7.bin and 000007.bin keeps 7, and an id that is no number is never padded."""
    from pipeline.frame import numbered_frame

    velodyne = tmp_path / "velodyne"
    velodyne.mkdir()
    for name in ("7", "000007", "00000a", "000012"):
        (velodyne / f"{name}.bin").write_bytes(b"")
    assert [numbered_frame(tmp_path, frame) for frame in ("7", "a", "12")] == ["7", "a", "000012"]


def test_the_lowest_pins_tool_refuses_a_prefix_of_its_flags(capsys: pytest.CaptureFixture[str]) -> None:
    """requirements/lowest.py is no member of the command family the other refusal test walks: --py was read
    as --python."""
    from requirements.lowest import main

    with pytest.raises(SystemExit) as refused:
        main(["--py", "3.10"])
    assert refused.value.code == 2
    assert "unrecognized arguments: --py 3.10" in capsys.readouterr().err


def _help(monkeypatch: pytest.MonkeyPatch, columns: int, **texts: str) -> str:
    """The --help at ``columns`` of a parser with the family's formatter: a flag with ``texts['help']``, a group
    with ``texts['group']`` as its description."""
    import argparse

    from pipeline.cli import HelpFormatter

    monkeypatch.setenv("COLUMNS", str(columns))
    parser = argparse.ArgumentParser(prog="x", formatter_class=HelpFormatter, allow_abbrev=False)
    group = parser.add_argument_group("mode", texts.get("group"))
    group.add_argument("--out", metavar="DIR", help=texts.get("help"))
    return parser.format_help()


def test_a_path_longer_than_the_help_column_stays_whole(monkeypatch: pytest.MonkeyPatch) -> None:
    """A word longer than the line (a path in an example) stands alone on its line, not cut at the width."""
    path = "/var/cache/lowres3d/tensorrt/engines-of-the-edge-model"
    text = _help(monkeypatch, 40, help=f"where the engines are kept, e.g. {path} on a vehicle")
    assert path in text.split(), text


def test_help_text_is_wrapped_as_words_whatever_its_spacing(monkeypatch: pytest.MonkeyPatch) -> None:
    """A help string written over several source lines or with doubled spaces reads as single-spaced words, as
    argparse's own wrapping gave."""
    text = _help(monkeypatch, 100, help="the run folder,\n        kept  as written")
    assert "the run folder, kept as written" in text, text


def test_a_group_description_keeps_its_indent_on_every_line(monkeypatch: pytest.MonkeyPatch) -> None:
    """A flag group's description is indented under its title: each of its wrapped lines, not the first only."""
    text = _help(monkeypatch, 40, group="what this group of flags does, said in more words than fit on a line")
    lines = text.split("mode:\n", 1)[1].split("\n\n", 1)[0].splitlines()
    assert len(lines) > 2 and all(line.startswith("  ") for line in lines), lines


def test_frame_ids_given_as_one_long_string_are_quoted_in_part() -> None:
    """A split file read whole into one string is thousands of characters: the TypeError quotes its first 20."""
    from evaluation.kitti_eval import bootstrap
    from tests.test_eval_intervals import frames, obj

    ids = "\n".join(f"{i:06d}" for i in range(100))
    with pytest.raises(TypeError) as refused:
        bootstrap(frames([obj()]), [frames([obj(score=0.9)])], resamples=1, frame_ids=ids)
    assert str(refused.value) == f"frame_ids: one id per frame, not the string {ids[:20]!r}"
