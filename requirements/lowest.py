"""The lowest versions pyproject.toml's runtime dependencies admit, as pip requirements (name==bound each).

    python requirements/lowest.py                  # every dependency, its environment marker kept
    python requirements/lowest.py --python 3.10    # those for Python 3.10, markers evaluated

A user who installs the wheel where older packages already are gets exactly these versions, so the runtime's
tests are run on them in a throwaway venv without torch (docs/deploy.md, "Lowest versions"). It installs nothing.

As a pytest plugin there (``-p requirements.lowest``, the checkout on PYTHONPATH) it has the tests' models
(export.exporter.run) exported by another interpreter that has torch, ``LOWRES3D_EXPORT_PYTHON`` (default the
checkout's .venv): the runtime under test loads them as a deployed runtime loads files exported elsewhere.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import re
import subprocess
import sys
import types
from pathlib import Path
from typing import Any

from packaging.requirements import InvalidRequirement, Requirement

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script: the repository's packages

from pipeline.cli import HelpFormatter, examples

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = ROOT / "pyproject.toml"
LOWER = (">=", "~=", "==")  # the specifiers whose version is the lowest one admitted
EXPORT_PYTHON = ROOT / ".venv" / "bin" / "python"  # the dev environment (make setup-dev), which has torch
# Run by that interpreter: export.exporter.run with the keywords given as JSON, paths as strings.
EXPORT = """
import json, sys
from pathlib import Path
from export.exporter import ExportConfig, run
fields = json.loads(sys.argv[1])
for key in ("out", "checkpoints", "kitti_dir"):
    if fields.get(key) is not None:
        fields[key] = Path(fields[key])
if "networks" in fields:
    fields["networks"] = tuple(fields["networks"])
run(ExportConfig(**fields))
"""


def lower_bound(requirement: Requirement) -> str:
    """The version of ``requirement``'s lower bound (``numpy>=1.26,<3`` → ``1.26``). ValueError naming the
    requirement when it has none: pip would take the newest release, and no lowest one can be tested."""
    bounds = [spec.version for spec in requirement.specifier if spec.operator in LOWER]
    if len(bounds) != 1:
        raise ValueError(f"{requirement}: expected one lower bound ({', '.join(LOWER)}), found {len(bounds)}")
    return bounds[0]


def lowest_pins(pyproject: Path = PYPROJECT, python: str | None = None) -> list[str]:
    """``name==bound`` for each of ``pyproject``'s [project].dependencies, in its order. Without ``python`` each
    keeps its environment marker (pip evaluates it); with one (``3.10``) only those it admits, without markers.
    ValueError naming the file when it is no TOML with dependencies, or one does not parse or has no lower bound."""
    import tomllib  # Python 3.11: here, so that the plugin loads in a 3.10 venv

    try:
        listed = tomllib.loads(pyproject.read_text())["project"]["dependencies"]
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{pyproject}: not TOML ({exc})") from exc
    except KeyError as exc:
        raise ValueError(f"{pyproject}: no [project] dependencies") from exc
    pins = []
    for text in listed:
        try:
            requirement = Requirement(text)
        except InvalidRequirement as exc:  # packaging's message spans lines (a caret under the place): the first
            raise ValueError(f"{pyproject}: {text!r}: {str(exc).splitlines()[0]}") from exc
        try:
            bound = lower_bound(requirement)
        except ValueError as exc:
            raise ValueError(f"{pyproject}: {exc}") from exc
        extras = f"[{','.join(sorted(requirement.extras))}]" if requirement.extras else ""
        pin = f"{requirement.name}{extras}=={bound}"
        marker = requirement.marker
        if marker is None:
            pins.append(pin)
        elif python is None:
            pins.append(f"{pin}; {marker}")
        elif marker.evaluate({"python_version": python, "python_full_version": f"{python}.0"}):
            pins.append(pin)
    return pins


def python_version(text: str) -> str:
    """A Python version as markers compare it, ``3.10`` (argparse type)."""
    if not re.fullmatch(r"3\.\d+", text):
        raise argparse.ArgumentTypeError(f"expected a version such as 3.10, got {text!r}")
    return text


# What the plugin leaves out of a run, by reason: test files that cannot run in the runtime's venv, or that time
# the benchmarks (benchmarks/ is not in the wheel), and single tests of other files that need torch.
LEFT_OUT = {
    "torch (models/, export/'s exporter)": (
        "test_benchmarks_mutants.py", "test_cache_pseudo.py", "test_depth_bound.py", "test_export.py",
        "test_export_stage_mutants.py", "test_models.py", "test_models_io_mutants.py", "test_models_review_s49.py",
        "test_networks_mutants.py", "test_onnx_weights.py", "test_own_sensor_training.py", "test_paper_fidelity.py",
        "test_preset_commands_s49.py", "test_preset_files.py", "test_reproduce.py", "test_run_checks_mutants.py",
        "test_schedule.py", "test_train_cli.py", "test_train_curves.py", "test_train_data.py", "test_train_init.py",
        "test_train_loop_mutants.py", "test_train_losses.py", "test_train_resume.py", "test_train_schedule.py",
        "test_train_soft_bev.py", "test_train_validation.py", "test_training.py", "test_training_presets_s49.py",
        "test_bad_files.py::test_cache_pseudo_names_the_frame_the_detector_refused",
        "test_lowest_bounds.py::test_the_plugin_has_the_models_exported_by_the_interpreter_with_torch",
        "test_model_tools_mutants.py::test_depth_parity_is_relative_so_far_depths_may_differ_by_more_than_a_millimetre",
        "test_model_tools_mutants.py::test_regression_parity_scales_with_the_maps_largest_value_and_every_failure_is_listed",
        "test_model_tools_mutants.py::test_an_error_equal_to_its_tolerance_passes",
        "test_pictures_s50.py::test_a_one_epoch_runs_curves_show_its_rate_and_validation_loss_on_whole_epochs",
        "test_input_guards_mutants.py::test_a_resume_on_the_same_frames_in_another_order_or_split_otherwise_is_refused",
        "test_input_guards_mutants.py::test_a_resume_on_other_validation_frames_is_refused_naming_the_validation_flags",
        "test_input_guards_mutants.py::test_label_files_that_name_nothing_are_said_to_be_empty",
        "test_input_guards_mutants.py::test_a_car_weight_below_1_with_no_car_to_weigh_is_refused_too",
        "test_input_guards_mutants.py::test_a_pseudo_pixor_whose_preset_record_has_no_depth_section_loads",
        "test_input_guards_mutants.py::test_a_pixor_that_learned_on_farther_pseudo_points_is_refused_under_a_nearer_range",
        "test_input_guards_mutants.py::test_a_state_from_before_the_frame_record_is_not_compared",
        "test_input_guards_mutants.py::test_a_run_with_its_own_validation_frames_resumes",
        "test_s49_guards_mutants.py::test_export_folder_stays_one_numbered_component",
        "test_s51_fixes.py::test_latency_refuses_checkpoints_that_do_not_fit_in_one_line",
        "test_s51_fixes.py::test_reproduce_quick_keeps_its_frames_in_out_and_bars_can_be_hidden",
        "test_s51_guards_mutants.py::test_the_torch_twin_refuses_a_folder_without_checkpoints_in_one_line"),
    "the dev tools (mypy, hadolint, vermin, setuptools) and the lock": (
        "test_typing.py", "test_container.py", "test_packaging.py", "test_lock.py"),
    "the command family, torch's commands among them": (
        "test_commands.py", "test_docs_commands.py",
        "test_s51_fixes.py::test_help_lines_break_at_spaces_only_so_a_flag_is_never_cut_in_two",
        "test_s51_fixes.py::test_no_command_reads_a_prefix_of_a_flag_as_the_flag"),
    "the timing benchmarks": ("test_latency.py", "test_latency_cli.py", "test_load.py", "test_bench_latency.py",
                              "test_bench_load.py", "test_bench_peak.py"),
}


class ExportConfig(types.SimpleNamespace):
    """export.exporter.ExportConfig's keywords, carried to the interpreter that exports."""


def export_elsewhere(config: ExportConfig) -> None:
    """export.exporter.run(config) in the interpreter with torch; CalledProcessError when it fails."""
    fields = {name: str(value) if isinstance(value, Path) else value for name, value in vars(config).items()}
    python = os.environ.get("LOWRES3D_EXPORT_PYTHON", str(EXPORT_PYTHON))
    subprocess.run([python, "-c", EXPORT, json.dumps(fields)], cwd=ROOT, check=True)


def pytest_configure(config: Any) -> None:
    """Leaves out what :data:`LEFT_OUT` names; without torch here, export.exporter is one whose run exports in
    the interpreter that has it."""
    named = [f"tests/{name}" for names in LEFT_OUT.values() for name in names]
    config.option.ignore = [*(config.option.ignore or []), *(str(ROOT / n) for n in named if "::" not in n)]
    config.option.deselect = [*(config.option.deselect or []), *(n for n in named if "::" in n)]
    if importlib.util.find_spec("torch") is None:
        exporter = types.ModuleType("export.exporter")
        exporter.ExportConfig, exporter.run = ExportConfig, export_elsewhere  # type: ignore[attr-defined]
        sys.modules["export.exporter"] = exporter


def main(argv: list[str] | None = None) -> int:
    """Print the pins, one a line; 2 with one line naming the file when it cannot be read or pinned."""
    parser = argparse.ArgumentParser(allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
                                     prog="python requirements/lowest.py", description=__doc__.split("\n\n")[0],
                                     epilog=examples("python requirements/lowest.py --python 3.10"),
                                     formatter_class=HelpFormatter)
    parser.add_argument("--python", type=python_version, metavar="X.Y",
                        help="only the dependencies this Python takes, their markers evaluated")
    parser.add_argument("--pyproject", type=Path, default=PYPROJECT, metavar="FILE",
                        help=f"the project file (default {PYPROJECT.relative_to(ROOT)})")
    args = parser.parse_args(argv)
    try:
        pins = lowest_pins(args.pyproject, args.python)
    except OSError as exc:
        print(f"error: --pyproject {args.pyproject}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except ValueError as exc:  # names the file and what is wrong in it
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print("\n".join(pins))
    return 0


if __name__ == "__main__":
    sys.exit(main())
