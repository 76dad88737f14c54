"""The documentation's command lines against the commands. Every ``python -m …`` of the project,
``python benchmarks/….py …`` (or ``benchmarks/….py …`` alone), ``python requirements/lock.py …`` and ``make …``
in README.md and docs/*.md, in a backtick span (wrapped across lines or not) or on a line of a fenced block
(``\\`` continuations joined), is parsed by the command's own argparse parser without running it, spells its
flags as --help shows them (not a hidden old alias, not an abbreviation argparse expands), and names a target
the Makefile has. No code in the docs names an old spelling, even outside a command, and each command's --help
examples parse too.

How a documented line is read, the rules kept few:

- A placeholder value (``DIR``, ``RUN``, ``N``, ``$input``: all capitals, digits and ``_``, or a shell variable)
  is a string; given to a flag that takes a number or one of a few choices, a valid one.
- A synopsis's optional part in brackets (``[--threads N]``) is not parsed, only its flags' names checked;
  alternatives ``a|b`` (``depth|detector|joint``, ``fp16\\|int8`` in a table) are read as their first.
- An ellipsis (``…``, ``...``) is an elided value after a flag that takes one, else left out.
- A backtick span may name a command with only the flags its sentence is about, so it may leave out required
  arguments and end on a flag it names (``python -m export --out``); a fenced block's lines are whole commands.
- ``python -m service: …`` (the program's name and a colon) is a message the command prints, not a command.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import shlex
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import pytest

from tests.test_commands import MODULES, OLD_SPELLINGS, SCRIPTS, _parser

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
PACKAGES = ("pipeline", "service", "simulation", "models", "export", "evaluation", "benchmarks", "requirements")
# Commands the docs run that are not in the family's list (tests/test_commands.py's FAMILY).
OTHERS: list[str] = []

_AFTER = r"(?:^|(?<=[\s;&|(]))"  # a command starts a segment or follows a blank or a shell operator
START = re.compile(
    _AFTER + r"(?:[\w./-]*/)?python(?:3(?:\.\d+)?)?\s+-m\s+(?P<module>[\w.]+)(?![\w./:])"  # `prog:` is a message
    + r"|" + _AFTER + r"(?:(?:[\w./-]*/)?python(?:3(?:\.\d+)?)?\s+)?(?P<script>(?:benchmarks|requirements)/\w+\.py)"
    r"(?![\w./:])"
    + r"|" + _AFTER + r"make\s+(?P<target>[a-z][\w-]*)")
PLACEHOLDER = re.compile(r"[A-Z][A-Z0-9_]*|\$\{?\w+\}?")
ELLIPSIS = ("…", "...")
FLAG = re.compile(r"(?<![\w-])--[a-z][\w-]*")
# A backtick span: a run of backticks to the same run, inside one paragraph.
SPAN = re.compile(r"(?<!`)(`+)(?!`)((?:(?!\n[ \t>]*\n).)+?)(?<!`)\1(?!`)", re.DOTALL)


@dataclass(frozen=True)
class Segment:
    """A piece of code in a markdown text: its first line's number, its text, and whether a backtick span."""

    line: int
    code: str
    inline: bool


@dataclass(frozen=True)
class DocCommand:
    """One documented command: where (``docs/x.md:12``), its name (``pipeline.detect``, ``latency``, ``make``),
    the arguments parsed, every flag written (optional parts too), its text, and whether in a backtick span."""

    where: str
    name: str
    args: tuple[str, ...]
    flags: tuple[str, ...]
    text: str
    inline: bool


def code_segments(markdown: str) -> list[Segment]:
    """Each logical line of a fenced block other than python, json or yaml (a synopsis's indented ``[…]`` lines
    joined to the line above), and each backtick span (its line breaks as blanks, a table's ``\\|`` as ``|``)."""
    segments = []
    prose = []
    fence, language, pending, opened_at = None, "", None, 0
    for number, line in enumerate(markdown.splitlines(), 1):
        opened = re.match(r"\s*(`{3,}|~{3,})\s*(\w*)", line)
        if fence is None and opened:
            fence, language, opened_at = opened.group(1), opened.group(2), number
        elif fence is not None and line.strip().startswith(fence):
            fence = None
        elif fence is not None and language not in ("python", "json", "yaml"):
            start, text = pending or (number, "")
            pending = (start, text + line[:-1] + " ") if line.endswith("\\") else None
            if pending is None and re.match(r"\s+\[", line) and segments and segments[-1].line > opened_at:
                segments[-1] = Segment(segments[-1].line, f"{segments[-1].code} {line.strip()}", inline=False)
            elif pending is None:
                segments.append(Segment(start, text + line, inline=False))
        prose.append("" if fence is not None or opened else line)
    text = "\n".join(prose)
    for span in SPAN.finditer(text):
        code = re.sub(r"[ \t]*\n[ \t>]*", " ", span.group(2)).replace("\\|", "|")
        segments.append(Segment(text.count("\n", 0, span.start()) + 1, code, inline=True))
    return sorted(segments, key=lambda s: s.line)


def _command_name(start: re.Match[str]) -> str | None:
    """The family's name of a command start (or ``make``); None for another program's module (``pytest``)."""
    if start.group("target"):
        return "make"
    if start.group("script"):
        script = start.group("script")
        return "requirements.lock" if script == "requirements/lock.py" else Path(script).stem
    module = start.group("module").removesuffix(".__main__")
    if module.split(".")[0] not in PACKAGES:
        return None
    return module.split(".", 1)[1] if module.startswith("benchmarks.") else module


def _split(text: str) -> tuple[list[str], list[str]]:
    """The argument tokens of a command from the text after its start, up to a shell operator or a comment (the
    synopsis's optional parts and alternatives read as the module's docstring says), and the flags of its
    optional parts."""
    optional = []
    for _ in range(2):  # a bracket inside a bracket: the inner one first
        optional += re.findall(r"\[([^\[\]]*)\]", text)
        text = re.sub(r"\[[^\[\]]*\]", " ", text)
    text = re.sub(r"(?<![\s|])\|(?![\s|])[^\s;&()]*", "", text)  # alternatives a|b|c: the first
    lexer = shlex.shlex(text, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    tokens = []
    for token in lexer:
        if set(token) <= set("();<>|&"):
            break
        tokens.append(token)
    return tokens, [flag for part in optional for flag in FLAG.findall(part)]


def _commands_in(segment: Segment, where: str) -> Iterator[DocCommand]:
    starts = list(START.finditer(segment.code))
    for i, start in enumerate(starts):
        name = _command_name(start)
        if name is None:
            continue
        end = starts[i + 1].start() if i + 1 < len(starts) else len(segment.code)
        rest = segment.code[start.end():end]
        if name == "make":
            args, optional = [start.group("target")], []
        else:
            try:
                args, optional = _split(rest)
            except ValueError as exc:  # an unclosed quote: the parse test reports it
                args, optional = [f"<cannot split the line: {exc}>"], []
        flags = [arg.split("=", 1)[0] for arg in args if FLAG.fullmatch(arg.split("=", 1)[0])] + optional
        yield DocCommand(f"{where}:{segment.line}", name, tuple(args), tuple(flags), (start.group(0) + rest).strip(),
                         segment.inline)


def doc_commands(markdown: str, where: str) -> list[DocCommand]:
    """Every command of the project in a markdown text (``where``: its name in the reports)."""
    return [command for segment in code_segments(markdown) for command in _commands_in(segment, where)]


def _docs() -> list[tuple[str, str]]:
    return [(str(doc.relative_to(REPO)), doc.read_text(encoding="utf-8")) for doc in DOCS]


@cache
def all_doc_commands() -> tuple[DocCommand, ...]:
    return tuple(command for where, text in _docs() for command in doc_commands(text, where))


@cache
def parser_of(name: str) -> argparse.ArgumentParser:
    """The parser the command's main builds, got as tests/test_commands.py gets it."""
    with pytest.MonkeyPatch.context() as patch:
        return _parser(name, patch)


def _parsers(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """A parser and its subcommands' parsers."""
    found = [parser]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in dict.fromkeys(action.choices.values()):
                found += _parsers(sub)
    return found


def _action_of(parser: argparse.ArgumentParser, flag: str) -> argparse.Action | None:
    return next((p._option_string_actions[flag] for p in _parsers(parser) if flag in p._option_string_actions), None)


def _takes_value(action: argparse.Action | None) -> bool:
    return action is not None and action.nargs != 0


def _arguments(parser: argparse.ArgumentParser, command: DocCommand) -> list[str]:
    """The command's arguments as parsed: ellipses and placeholders read as the module's docstring says."""
    args: list[str] = []
    for token in command.args:
        after_flag = bool(args) and _takes_value(_action_of(parser, args[-1]))
        if token in ELLIPSIS:
            if not after_flag:
                continue
            token = "X"  # an elided value, read as a placeholder
        action = _action_of(parser, args[-1]) if after_flag else None
        if action is not None and PLACEHOLDER.fullmatch(token):
            if action.choices:
                token = str(next(iter(action.choices)))
            elif action.type not in (None, str, Path):
                try:
                    action.type(token)
                except (ValueError, TypeError, argparse.ArgumentTypeError):
                    token = "1"
        args.append(token)
    if command.inline and args and _takes_value(_action_of(parser, args[-1])):
        args.pop()  # the flag a sentence is about
    return args


@contextlib.contextmanager
def _nothing_required(parser: argparse.ArgumentParser, inline: bool) -> Iterator[None]:
    """For a backtick span, no argument required while parsing (a sentence names only the flags it is about)."""
    actions = [a for p in _parsers(parser) for a in p._actions if a.required] if inline else []
    for action in actions:
        action.required = False
    try:
        yield
    finally:
        for action in actions:
            action.required = True


def parse_error(command: DocCommand) -> str | None:
    """argparse's message for a documented command line, None when it parses."""
    parser = parser_of(command.name)
    stderr = io.StringIO()
    try:
        with (_nothing_required(parser, command.inline), contextlib.redirect_stderr(stderr),
              contextlib.redirect_stdout(io.StringIO())):
            parser.parse_args(_arguments(parser, command))
    except SystemExit as exc:
        if exc.code:
            return stderr.getvalue().strip().splitlines()[-1]
    return None


def wrong_spellings(command: DocCommand) -> list[str]:
    """The flags of a documented command not written as --help shows them: a hidden old alias (with its current
    name), or no flag of the command's (an abbreviation argparse expands, or unknown)."""
    from pipeline.cli import shown_spellings

    parser = parser_of(command.name)
    wrong = []
    for flag in command.flags:
        action = _action_of(parser, flag)
        if action is None:
            wrong.append(f"{flag} (no flag of its own: an abbreviation or unknown)")
        elif flag not in shown_spellings(action):
            wrong.append(f"{flag} (an old spelling of {shown_spellings(action)[-1]})")
    return wrong


def old_spellings_in(segment: Segment) -> list[str]:
    """The hidden old spellings a piece of code uses anywhere (a flag named in a sentence too); ``--beams`` is
    pipeline.beams' own flag, so only an old spelling where no pipeline.beams command is."""
    used = [flag for flag in FLAG.findall(segment.code) if flag in OLD_SPELLINGS]
    if "pipeline.beams" in segment.code:
        used = [flag for flag in used if flag != "--beams"]
    return used


def makefile_targets(makefile: str) -> set[str]:
    """The targets a Makefile's rules name (``a b: deps``), variables' assignments (``X := …``) left out."""
    return {target for names in re.findall(r"^([^\s#:=][^:=\n]*):(?![=:])", makefile, re.MULTILINE)
            for target in names.split()}


def _report(problems: list[str]) -> str:
    return f"{len(problems)} in the documentation:\n" + "\n".join(problems)


def test_every_documented_command_parses():
    problems = [f"{c.where}: `{c.text}`: {error}" for c in all_doc_commands() if c.name != "make"
                for error in [parse_error(c)] if error]
    assert not problems, _report(problems)


def test_documented_commands_spell_their_flags_as_help_shows_them():
    problems = [f"{c.where}: `{c.text}`: {', '.join(wrong)}" for c in all_doc_commands() if c.name != "make"
                for wrong in [wrong_spellings(c)] if wrong]
    assert not problems, _report(problems)


def test_no_code_in_the_docs_uses_an_old_spelling():
    problems = [f"{where}:{s.line}: `{s.code.strip()}`: {', '.join(f'{old} (now {OLD_SPELLINGS[old]})' for old in used)}"
                for where, text in _docs() for s in code_segments(text) for used in [old_spellings_in(s)] if used]
    assert not problems, _report(problems)


def test_every_documented_make_target_exists():
    targets = makefile_targets((REPO / "Makefile").read_text())
    assert {"demo", "test", "lint"} <= targets, targets
    problems = [f"{c.where}: `{c.text}`: no target {c.args[0]} in the Makefile" for c in all_doc_commands()
                if c.name == "make" and c.args[0] not in targets]
    assert not problems, _report(problems)


def test_the_extraction_finds_the_documented_commands():
    """Every command of the family the docs run is found, and no other (a broken pattern would find none)."""
    names = {c.name for c in all_doc_commands()}
    assert {"pipeline.detect", "service", "simulation", "models.train", "export", "latency", "accuracy",
            "requirements.lock", "make"} <= names, names
    assert names - {"make"} <= set(MODULES + SCRIPTS + OTHERS), names
    assert sum(not c.inline for c in all_doc_commands()) > 50 and len(all_doc_commands()) > 200


# The extraction on small texts, a rule a case.
READ = [
    ("Run `python -m simulation --out DIR\n--frames 2` here.", [("x.md:1", "simulation", ("--out", "DIR", "--frames", "2"))]),
    ("a\n\n```bash\npython benchmarks/latency.py --models DIR \\\n    --json out.json  # --note\nmake lint\n```\n",
     [("x.md:4", "latency", ("--models", "DIR", "--json", "out.json")), ("x.md:6", "make", ("lint",))]),
    ("| `python -m export --preset P [--precision fp16\\|int8]` |", [("x.md:1", "export", ("--preset", "P"))]),
    ("`python -m models.train depth\\|detector\\|joint --data DIR …`",
     [("x.md:1", "models.train", ("depth", "--data", "DIR", "…"))]),
    ("`cd x && .venv/bin/python -m service --port 1 & python -m pytest -q`", [("x.md:1", "service", ("--port", "1"))]),
    ("```python\nimport x  # python -m service\n```\n`make demo`, `benchmarks/peak.py --top 3`",
     [("x.md:4", "make", ("demo",)), ("x.md:4", "peak", ("--top", "3"))]),
    ("```\npython -m service: --token: empty\n```", []),  # a message the command prints, not a command
    ("```\npython benchmarks/accuracy.py --gt-labels DIR [--json OUT]\n        [--bootstrap N [--seed S]]\n```",
     [("x.md:2", "accuracy", ("--gt-labels", "DIR"))]),
]


@pytest.mark.parametrize(("markdown", "expected"), READ)
def test_the_extraction_reads_each_form(markdown, expected):
    assert [(c.where, c.name, c.args) for c in doc_commands(markdown, "x.md")] == expected


@pytest.mark.parametrize(("markdown", "error"), [
    ("`python -m simulation --out DIR --frames 0`", "argument --frames: must be at least 1, got 0"),
    ("`python -m simulation --out DIR --colour red`", "unrecognized arguments: --colour red"),
    ("```\npython -m simulation --out DIR\n```", "the following arguments are required: --frames, --seed"),
    ("`python -m models.train depth --preset edge … --out`", None),  # a span: a fragment naming --out
    ("`python -m models.train joint --depth-checkpoint … --epochs 1`", None),
    ("`python -m simulation --out DIR --frames N --seed S`", None),
    ("```\nfor i in lidar64 lidar16; do python -m models.train detector --input $i --data D --out R; done\n```", None),
])
def test_a_documented_command_is_parsed_as_the_rules_say(markdown, error):
    [command] = doc_commands(markdown, "x.md")
    found = parse_error(command)
    assert found == error if error is None else found.endswith(error), found


def test_wrong_spellings_are_named():
    [command] = doc_commands("`python benchmarks/sim_report.py --kitti D --figure a.png --sim-dat S [--framez N]`",
                             "x.md")
    # The old names are hidden aliases argparse takes; an abbreviation it refuses since every command has
    # allow_abbrev=False (session 51: --frame was read as --frames).
    assert parse_error(command).endswith("error: unrecognized arguments: --sim-dat S")
    assert wrong_spellings(command) == ["--kitti (an old spelling of --data)", "--figure (an old spelling of --plot)",
                                        "--sim-dat (no flag of its own: an abbreviation or unknown)",
                                        "--framez (no flag of its own: an abbreviation or unknown)"]
    [beams] = doc_commands("`python -m pipeline.beams --beams 16 A B`", "x.md")
    assert wrong_spellings(beams) == []
    assert old_spellings_in(Segment(1, "--beams 0 --kitti D", inline=True)) == ["--beams", "--kitti"]


def test_makefile_targets_are_read_from_its_rules():
    assert makefile_targets("X := a:b\n.PHONY: demo\ndemo test: x\n\t$(BIN)/python -m x: y\n# c: d\n") == {
        ".PHONY", "demo", "test"}


def help_examples(name: str) -> list[DocCommand]:
    """The example command lines of a command's --help (its epilog's indented lines), read as a fenced block's."""
    epilog = parser_of(name).epilog or ""
    lines = [line.strip() for line in epilog.splitlines() if line.startswith("  ")]
    return [c for c in doc_commands("```\n" + "\n".join(lines) + "\n```", f"{name} --help") if c.name != "make"]


@pytest.mark.parametrize("name", [*MODULES, *SCRIPTS])
def test_the_examples_of_each_help_parse(name):
    """--help's examples are documentation too: each a whole command, in current names."""
    examples = help_examples(name)
    assert examples, name  # every command of the family shows one (tests/test_commands.py)
    problems = [f"`{c.text}`: {problem}" for c in examples for problem in [parse_error(c), *wrong_spellings(c)]
                if problem]
    assert not problems, _report(problems)
