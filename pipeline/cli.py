"""Argument types and output checks shared by the commands: numbers that must be positive are refused by
argparse itself, output files that cannot be written before any work; how a command says Ctrl-C
stopped it (:func:`interrupted`, :func:`quiet_interrupt`); and what makes the commands one family: their
--help (:class:`HelpFormatter`, :func:`examples`), their progress bars (:func:`add_no_progress`,
:func:`show_progress`) and a flag's old spellings (hidden aliases, :func:`as_given`).

A count of 0 is not "the default": ``--epochs 0`` used to fall through to the recipe's 30 epochs.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import functools
import importlib.util
import os
import re
import signal
import sys
import textwrap
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

from pipeline.errors import InputError


def positive_int(text: str) -> int:
    """An integer ≥ 1 (argparse type)."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def list_or_count(value: str) -> Path | int:
    """--frames: a file of frame ids, or a count N (digits naming no file) for the first N frames."""
    if value.isdigit() and not Path(value).exists():
        return positive_int(value)
    return Path(value)


def non_negative_int(text: str) -> int:
    """An integer ≥ 0 (argparse type)."""
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {value}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0 (argparse type)."""
    value = float(text)
    if not (0 < value < float("inf")):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def probability(text: str) -> float:
    """A number in [0, 1] (argparse type), such as a score threshold."""
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be between 0 and 1, got {text}")
    return value


def gpu_ids(text: str) -> list[int]:
    """GPU ids separated by commas, ``0,1`` (argparse type; the service's ``--device-ids`` too): each a whole
    number from 0, none twice."""
    ids = []
    for part in text.split(","):
        part = part.strip()
        if not part.isdigit():
            raise argparse.ArgumentTypeError(f"expected GPU ids from 0 separated by commas (0,1), got {text!r}")
        ids.append(int(part))
    if len(set(ids)) != len(ids):
        raise argparse.ArgumentTypeError(f"a GPU id given twice in {text!r}")
    return ids


def frame_rate(text: str) -> float:
    """Frames a second of a video (argparse type), 0.1 to 1000: OpenCV's MP4 writer fails outside 0.01–65535,
    and beyond those bounds no video of driving frames is meant (a frame every 10 s, or 100 times real time)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0.1 <= value <= 1000:
        raise argparse.ArgumentTypeError(f"must be from 0.1 to 1000 frames a second, got {text}")
    return value


def unwritable(out: object, exc: OSError) -> str:
    """The one-line error for an output folder the system refused (a file in the way, no permission, full)."""
    where = f"{exc.filename}: " if exc.filename and str(exc.filename) != str(out) else ""  # each path once
    return f"error: --out {out}: {where}{exc.strerror or exc}"


def check_output(path: Path, flag: str, directory: bool = False) -> None:
    """Refuse, before any work, an output path that cannot be written: ``path`` is, or will be created
    as, a directory (``directory``) or a file in one; missing folders above it are made when it is
    written, so its nearest existing ancestor must be a writable directory."""
    path = Path(path)
    if path.exists():
        if directory and not path.is_dir():
            raise InputError(f"{flag} {path}: exists and is not a directory")
        if not directory and path.is_dir():
            raise InputError(f"{flag} {path}: is a directory; give a file name")
        if not os.access(path, os.W_OK):
            raise InputError(f"{flag} {path}: not writable")
        return
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise InputError(f"{flag} {path}: {parent} is a file, not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"{flag} {path}: cannot create it in {parent} (not writable)")


# The folders of a --data root that hold what a run reads (KITTI object and depth-completion layouts).
DATA_FOLDERS = ("image_2", "velodyne", "calib", "label_2", "depth_2", "ImageSets", "image_02", "velodyne_raw",
                "groundtruth")


def check_not_input(path: Path, flag: str, inputs: dict[str, Path | None]) -> None:
    """Refuse an output that would be written over what the run reads: an input (``inputs``: flag → path;
    None for one not given) itself, or a path inside an input folder. ``--data`` is a dataset root: there
    only its own folders (:data:`DATA_FOLDERS`) are refused, so a new folder in it may hold outputs."""
    out = Path(path).resolve()
    for name, source in inputs.items():
        if source is None:
            continue
        source = Path(source).resolve()
        read = [source / folder for folder in DATA_FOLDERS] if name == "--data" else [source]
        hit = next((r for r in read if out == r or r in out.parents), None)
        if out == source or hit is not None:
            raise InputError(f"{flag} {path}: would be written over what {name} {source} holds, which this run "
                             "reads; give a path outside it")


def check_not_inside(folder: Path, flag: str, inputs: dict[str, Path | None]) -> None:
    """Refuse an input that lies in ``folder`` (or is it), an output folder the run replaces whole once its new
    content is written (``inputs``: flag → path; None, or a path not there, skipped: its own check names it):
    ``python -m export --out M --data M/kitti`` deleted the frames it had just read."""
    out = Path(folder).resolve()
    for name, source in inputs.items():
        if source is None or not Path(source).exists():
            continue
        if Path(source).resolve() == out or out in Path(source).resolve().parents:
            raise InputError(f"{flag} {folder}: replacing it would delete {name} {source}, which this run reads; "
                             f"give another {flag}, one that does not hold it")


FIGURE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pdf", ".svg")  # what matplotlib writes from the file name


def check_figure(path: Path, flag: str) -> None:
    """:func:`check_output` for a picture, and a name matplotlib can write (else it fails after the run)."""
    if Path(path).suffix.lower() not in FIGURE_SUFFIXES:
        raise InputError(f"{flag} {path}: give a file name ending in {', '.join(FIGURE_SUFFIXES)}")
    if importlib.util.find_spec("matplotlib") is None:
        raise InputError(f"{flag}: drawing needs matplotlib, which the runtime install leaves out; install the dev "
                         "extras (make setup-dev) or .venv/bin/pip install 'matplotlib>=3.10'")
    check_output(path, flag)


def write_text_file(path: Path, text: str) -> None:
    """Write an output file checked by :func:`check_output`, making its folder first."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")


def skipped_summary(names: list[str], what: str, total: int | None = None) -> str:
    """The closing line of a run that went on past unusable inputs: ``3 of 300 frame(s) skipped (each named
    above with its reason): a, b, c`` (the first ten names, then how many more)."""
    more = f" and {len(names) - 10} more" if len(names) > 10 else ""
    of = f" of {total}" if total is not None else ""
    return f"{len(names)}{of} {what}(s) skipped (each named above with its reason): {', '.join(names[:10])}{more}"


INTERRUPTED_STATUS = 130  # 128 + SIGINT: what a shell reports for a command that Ctrl-C stopped


def interrupted(leaves: str) -> int:
    """Say in one line on stderr that Ctrl-C stopped the command, and what it leaves (``leaves``: what the
    user has now and how to go on), instead of a traceback. Returns the exit status, 130."""
    print(f"interrupted: {leaves}", file=sys.stderr)
    return INTERRUPTED_STATUS


# What Ctrl-C leaves while a command still loads its libraries (a second or two): nothing begun, nothing written.
STOPPED_LOADING = "while the command was loading PyTorch and ONNX, before it began; nothing was written"


def _stop_loading() -> None:
    """End the command with :func:`interrupted`'s line and 130, at once (os._exit): nothing is set up yet, and a
    SystemExit raised inside a library's initialisation could be caught there."""
    status = interrupted(STOPPED_LOADING)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


@contextlib.contextmanager
def ctrl_c_held_while_loading(command: bool) -> Iterator[None]:
    """Hold Ctrl-C within the block, a torch command's imports (PyTorch and ONNX load for a second or two, before
    any work), then end the command with one ``interrupted: …`` line and exit status 130; a second Ctrl-C ends it
    at once. Raised inside a library's initialisation, the KeyboardInterrupt printed a traceback and could abort
    the process from C++, be swallowed, or leave NumPy half-made. Only when ``command`` (the block runs on the way
    to a command's main) and in the main thread: an importer's own Ctrl-C (pytest, a notebook) stays theirs."""
    if not command or threading.current_thread() is not threading.main_thread():
        yield
        return
    pressed: list[int] = []

    def hold(signum: int, frame: object) -> None:
        if pressed:
            _stop_loading()
        pressed.append(signum)

    previous = signal.signal(signal.SIGINT, hold)
    try:
        yield
    except KeyboardInterrupt:  # one raised by other means than the signal
        _stop_loading()
    finally:
        signal.signal(signal.SIGINT, previous)
    if pressed:
        _stop_loading()


TERMINATED_STATUS = 143  # 128 + SIGTERM: what a shell reports for a command that `kill` or `timeout` stopped


class Terminated(KeyboardInterrupt):
    """SIGTERM (a cluster's pre-emption, `kill`, `timeout`, a service manager's stop), raised where the command
    is, so that it stops as Ctrl-C does: files being written abandoned whole, worker processes stopped, one line."""


def _raise_terminated(signum: int, frame: object) -> None:
    raise Terminated(signum)


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within the block SIGTERM raises :class:`Terminated`, for the long-running commands (pipeline.detect, training, models.reproduce, simulation)
    whose default end on SIGTERM would say nothing of what they kept. Outside the main thread, where Python sets
    no handler, the block runs with the signal as it was."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def stopped(exc: KeyboardInterrupt, leaves: str) -> int:
    """:func:`interrupted` for Ctrl-C; for SIGTERM (:class:`Terminated`) the same line as ``terminated: …`` and
    exit status 143, as if the signal had ended the command."""
    if not isinstance(exc, Terminated):
        return interrupted(leaves)
    print(f"terminated: {leaves}", file=sys.stderr)
    return TERMINATED_STATUS


Main = Callable[..., int]


def quiet_interrupt(leaves: str) -> Callable[[Main], Main]:
    """Decorate a command's ``main``: Ctrl-C ends it with :func:`interrupted`'s one line (for commands whose
    outputs are written at the end, so an interruption leaves the same thing whenever it comes)."""
    def decorate(main: Main) -> Main:
        @functools.wraps(main)
        def run(*args: object, **kwargs: object) -> int:
            try:
                return main(*args, **kwargs)
            except KeyboardInterrupt:
                return interrupted(leaves)
        return run
    return decorate


def _wrapped(text: str, width: int, indent: str = "") -> str:
    """``text``'s words in lines of at most ``width`` (a longer word alone on its line), each after ``indent``.
    Broken at spaces only: argparse's textwrap also breaks after a hyphen, which cut flags and paths in two
    ("--pixor-" at a line's end, "checkpoint" on the next), and a copied command then failed."""
    return textwrap.fill(" ".join(text.split()), max(width, 1), initial_indent=indent, subsequent_indent=indent,
                         break_on_hyphens=False, break_long_words=False)


class HelpFormatter(argparse.HelpFormatter):
    """Every command's --help. The description and the epilog: each paragraph fitted to the terminal, but one
    with an indented line (an example, a synopsis, a list) as written, so an example stays one command a line.
    The options: each flag under its family name alone. A flag's later long spellings are old names kept
    working for scripts (hidden aliases: ``add_argument("--emulate-beams", "--beams", …)``); --help leaves them
    out, but a --X/--no-X pair keeps its --no-X."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        paragraphs = []
        for paragraph in re.split(r"\n[ \t]*\n", text.strip("\n")):
            lines = paragraph.splitlines()
            if any(line[:1].isspace() for line in lines):
                paragraphs.append("\n".join(indent + line for line in lines))
            else:
                paragraphs.append(_wrapped(paragraph, width, indent))
        return "\n\n".join(paragraphs)

    def _split_lines(self, text: str, width: int) -> list[str]:
        return _wrapped(text, width).splitlines()

    def _format_action_invocation(self, action: argparse.Action) -> str:
        shown = shown_spellings(action)
        if shown == action.option_strings:
            return super()._format_action_invocation(action)
        named = copy.copy(action)
        named.option_strings = shown
        return super()._format_action_invocation(named)


def shown_spellings(action: argparse.Action) -> list[str]:
    """The option strings --help shows for ``action``: its short ones, its first long one (the family's name)
    and, for a --X/--no-X pair, the --no-X; the other long ones are hidden aliases."""
    longs = [s for s in action.option_strings if s.startswith("--")]
    pair = isinstance(action, argparse.BooleanOptionalAction)
    negated = [s for s in longs[1:] if pair and s.startswith("--no-")]
    return [s for s in action.option_strings if not s.startswith("--")] + longs[:1] + negated


def examples(*commands: str) -> str:
    """An epilog of example command lines under ``example:`` (``examples:`` for several), one a line, as
    :class:`HelpFormatter` shows them."""
    head = "example:" if len(commands) == 1 else "examples:"
    return "\n".join([head, *(f"  {command}" for command in commands)])


def as_given(argv: Sequence[str] | None, flag: str, *old: str) -> str:
    """How the command line spelled a flag that has old spellings (``old``, hidden aliases): the last one given,
    whose value argparse keeps, so that an error names the flag as the user wrote it; ``flag`` when none was."""
    given = [arg.split("=", 1)[0] for arg in (sys.argv[1:] if argv is None else argv)]
    return next((arg for arg in reversed(given) if arg in (flag, *old)), flag)


NO_PROGRESS_HELP = "no progress bars (they are drawn only when stderr is a terminal)"


def add_no_progress(parser: argparse.ArgumentParser | argparse._ArgumentGroup, help: str = NO_PROGRESS_HELP) -> None:
    """The family's --no-progress flag."""
    parser.add_argument("--no-progress", action="store_true", help=help)


def show_progress(no_progress: bool) -> bool:
    """Whether a command draws its progress bars: not with --no-progress, and only on a terminal. In a log or a
    pipe a bar is carriage returns, and each line written above it (``tqdm.write``: a frame skipped, a warning)
    came between the bar's copies and the blanks it was cleared with: read line by line, blank lines between."""
    return not no_progress and sys.stderr.isatty()


MISSING_EXTRA_STATUS = 2  # a package the runtime install leaves out: an input the command cannot use


def missing_extra(message: str) -> SystemExit:
    """What a command raises when the runtime install lacks a package it needs: ``message`` (one ``error: …``
    line saying what to install) on stderr, then exit status 2, as for any other usage error."""
    print(message, file=sys.stderr)
    return SystemExit(MISSING_EXTRA_STATUS)
