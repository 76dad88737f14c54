"""Check a model directory before it ships to vehicles: one PASS/FAIL line per check, and an exit status.

examples:
  python -m pipeline.check_models --models /srv/lowres3d/edge-v7
  python -m pipeline.check_models --models /srv/lowres3d/edge-v7 --provider tensorrt --json check.json
  python -m pipeline.check_models --models /srv/lowres3d/edge-v7 --provider tensorrt \\
      --trt-cache-dir /var/cache/lowres3d/tensorrt

The checks, in order (each needs the ones before it; those after a failure are reported as skipped):

  manifest  manifest.json reads: a format this lowres3d reads, the tables the runtime needs, a usable preset,
            trained weights (--allow-untrained for a latency-only export)
  files     every file it lists is there, of its listed size and sha256 (the first five bad files named, then
            how many more)
  sessions  ONNX Runtime loads each graph on --provider (the provider really used, no silent fallback), and the
            graphs' inputs and outputs (names, float32, shapes) are those of the manifest's preset; with
            tensorrt the engines are built in --trt-cache-dir (default MODELS/trt_cache/): given the
            service's cache, the check builds the engines the service will load, before its first frame
  frame     one real frame runs: each network's raw outputs finite and of the preset's shapes, the scores in
            [0, 1], the boxes finite

The frame is KITTI 000006 of the source checkout's tests/data (its 64-line scan thinned to the model's own line
count), or --data DIR --frame ID: a 64-line scan is thinned so too, and a scan with the model's line count already
(a 16-line vehicle's own frame for a 16-line model) runs as stored, the vehicle's real input; a scan thinned to
another count is refused (exit 2; --emulate-beams 0 runs any scan as stored). The last line gives the model's id,
the sha256 of its manifest.json: what the service reports in /v1/model, in each answer's X-Model-ID header and in
lowres3d_model_info. Exit status 0 when every check passes, 1 when one fails, 2 for an unusable command line (no
such --models folder, a frame that cannot be read or is thinned to another line count, an unwritable --json or one
inside what the check reads). Runs on the runtime install: ONNX Runtime, no torch.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from pipeline.beams import BEAM_COUNTS, emulate_beams, lines_to_thin_to, recover_rings
from pipeline.checks import WarningCode
from pipeline.cli import (
    HelpFormatter,
    check_not_input,
    check_output,
    examples,
    quiet_interrupt,
    write_text_file,
)
from pipeline.detector import Detector, resolve_providers
from pipeline.errors import InputError
from pipeline.frame import Frame, load_frame, numbered_frame
from pipeline.kitti import SAMPLE_DIR
from pipeline.model_files import (
    MANIFEST_NAME,
    ModelFileError,
    ModelIdentity,
    check_descriptions,
    load_manifest_with_digest,
    model_identity,
    verify_sha256,
)
from pipeline.presets import Preset, preset_from_dict

SAMPLE_FRAME = "000006"
CHECKS = ("manifest", "files", "sessions", "frame")
SHOWN_PROBLEMS = 5  # the bad files the files check names, before "and N more"


class CheckFailed(Exception):
    """A check found the directory unfit to ship; the message says why."""


@dataclass(frozen=True)
class CheckConfig:
    """What to check and how."""

    models: Path
    provider: str | None = None  # cpu, cuda or tensorrt; None: the best this ONNX Runtime offers
    data: Path | None = None  # a KITTI object folder; None: the checkout's bundled frames
    frame: str = SAMPLE_FRAME
    emulate_beams: int | None = None  # None: the model's own line count; 0: the scan as stored
    allow_untrained: bool = False
    trt_cache_dir: Path | None = None  # TensorRT's engine cache; None: MODELS/trt_cache, as the service's default


@dataclass
class Check:
    """One check's outcome: ``status`` is pass, fail or skip."""

    name: str
    status: str
    detail: str
    warnings: list[str] = field(default_factory=list)


@dataclass
class CheckReport:
    """Every check's outcome, and the model's identity once its manifest and files checked out."""

    models: str
    checks: list[Check]
    identity: ModelIdentity | None = None

    @property
    def passed(self) -> bool:
        return all(check.status == "pass" for check in self.checks)

    def to_dict(self) -> dict:
        return {"models": self.models, "passed": self.passed,
                "identity": asdict(self.identity) if self.identity is not None else None,
                "checks": [asdict(check) for check in self.checks]}


def check_manifest(models: Path, allow_untrained: bool) -> tuple[dict, str, Preset]:
    """The manifest, its sha256 and its preset; CheckFailed naming the field at fault."""
    try:
        manifest, digest = load_manifest_with_digest(models)
        preset = preset_from_dict(manifest["preset_config"])
    except (ModelFileError, ValueError) as exc:
        raise CheckFailed(str(exc)) from exc
    if "pixor" not in manifest.get("networks", {}):
        raise CheckFailed(f"{models / MANIFEST_NAME}: no 'pixor' network listed")
    try:  # the descriptions other runtimes read say what runs (a grid too broken to describe: the sessions' check)
        described = preset.described()
    except (ArithmeticError, TypeError, ValueError):
        described = None
    if described is not None:
        try:
            check_descriptions(manifest, described, models / MANIFEST_NAME)
        except ModelFileError as exc:
            raise CheckFailed(str(exc)) from exc
    untrained = [name for name, entry in manifest["networks"].items() if entry.get("weights") != "trained"]
    if untrained and not allow_untrained:
        raise CheckFailed(f"{models / MANIFEST_NAME}: {', '.join(untrained)}: exported without trained weights (their "
                          "boxes mean nothing); export trained checkpoints, or --allow-untrained for a latency test")
    return manifest, digest, preset


def check_files(models: Path, manifest: dict) -> list[str]:
    """Each listed file's size and sha256, every bad one named (not the first only); the directory's files the
    manifest does not list, as notes (a stale file is never loaded, but says the copy was not a clean one)."""
    problems = []
    for name, entry in manifest["files"].items():
        try:
            verify_sha256(models, {"files": {name: entry}})
        except ModelFileError as exc:
            problems.append(str(exc))
    if problems:  # a few named, then a count: a manifest may list 100,000 files, and the report stays readable
        more = f"; and {len(problems) - SHOWN_PROBLEMS} more" if len(problems) > SHOWN_PROBLEMS else ""
        raise CheckFailed("; ".join(problems[:SHOWN_PROBLEMS]) + more)
    listed = {MANIFEST_NAME, "trt_cache", *manifest["files"]}
    return [f"{models / name}: not listed in the manifest (never loaded)"
            for name in sorted(p.name for p in models.iterdir()) if name not in listed]


def frame_scan(detector: Detector, points: np.ndarray, emulate: int | None, source: Path) -> tuple[np.ndarray, str]:
    """The scan the frame check runs, and how it was read: thinned to ``--emulate-beams`` (0: as stored), else to
    the model's own line count (as stored for a 64-line model). A scan that cannot be thinned, being thinned
    already, runs as stored when it has the model's lines (a vehicle's own frame: what the model will see); an
    InputError naming ``source`` otherwise, as a frame unfit for the check is the command line's fault, not
    the model's."""
    beams = emulate if emulate is not None else lines_to_thin_to(detector.trained_lines)
    if not beams:
        return points, "as stored"
    try:
        return emulate_beams(points, beams), f"thinned to {beams} lines"
    except InputError as exc:
        why = str(exc)
    rings = recover_rings(points)  # thinned already: how many lines, when its scan order tells (not out of order)
    # A ring-ordered scan splits into one segment per ring, and one more when its first ring is cut at the wrap.
    if emulate is None and rings.method == "azimuth-wrap" and beams <= rings.n_rings <= beams + 1:
        return points, f"as stored: {beams} lines already, the model's own"
    # The way out beams.check_scan_thinnable names for such a scan in the training and evaluation commands.
    raise InputError(f"{source}: {why}; to check the model on a sensor's scans as they are, give --emulate-beams 0")


def _finite(name: str, array: np.ndarray, shape: tuple[int, ...] | None = None) -> None:
    """CheckFailed when ``array`` holds NaN or infinity, or is not of ``shape``."""
    if shape is not None and tuple(array.shape) != shape:
        raise CheckFailed(f"{name}: shape {list(array.shape)}, where the preset gives {list(shape)}")
    bad = int(np.count_nonzero(~np.isfinite(array)))
    if bad:
        raise CheckFailed(f"{name}: {bad} of {array.size} values are NaN or infinite")


def check_frame(detector: Detector, frame: Frame, points: np.ndarray, scan: str) -> str:
    """Run one frame on its scan ``points`` (read as ``scan`` says, :func:`frame_scan`): each network's raw
    outputs, then the boxes; CheckFailed naming the output at fault."""
    inputs = detector.network_inputs(frame.image, points, frame.calib)  # what detect() feeds each network
    preset = detector.preset
    if detector.two_stage:
        depth = detector.run_depth_net(inputs["depth"]["rgb"], inputs["depth"]["sparse_depth"])
        _finite("depth.onnx output depth", depth, tuple(preset.depth.input_hw))
    stride = preset.pixor.output_stride
    maps = (preset.bev.ny // stride, preset.bev.nx // stride)
    # The raw maps: a NaN score is never above the threshold, so the boxes alone would pass as "no car".
    score, regression = detector.run_pixor(inputs["pixor"]["bev"])
    _finite("pixor.onnx output score", score, (1, 1, *maps))
    _finite("pixor.onnx output regression", regression, (1, 6, *maps))
    if score.min() < 0 or score.max() > 1:
        raise CheckFailed(f"pixor.onnx output score: values from {score.min():.3g} to {score.max():.3g}, not in [0, 1]")
    tic = time.perf_counter()
    result = detector.detect(frame.image, points, frame.calib)
    elapsed = (time.perf_counter() - tic) * 1e3
    _finite("boxes", result.boxes)
    _finite("scores", result.scores)
    # Named, not failed: a frame unlike the model's training (a 16-line scan for a 64-line model) is no fault
    # of the files, but the person rolling them out should see it.
    codes = [code for code in result.warning_codes if code != WarningCode.BEAMS_EMULATED]
    warned = f"; the frame's warnings: {', '.join(codes)}" if codes else ""
    return (f"frame {frame.frame_id} (scan {scan}): {len(result.scores)} car(s), every output finite, "
            f"{elapsed:.0f} ms{warned}")


def frame_folder(config: CheckConfig) -> Path:
    """The KITTI object folder the frame is read from: ``--data``, else the checkout's bundled frames."""
    return config.data if config.data is not None else SAMPLE_DIR


def read_frame(config: CheckConfig) -> Frame:
    """The frame to run; InputError when it cannot be read (the bundled one exists only in a source checkout)."""
    data = frame_folder(config)
    if config.data is None and not data.is_dir():
        raise InputError(f"--data: the bundled frames ({data}) exist only in a source checkout; give --data DIR "
                         "--frame ID (a KITTI object folder)")
    return load_frame(data, numbered_frame(data, config.frame), with_labels=False)


@contextmanager
def _recorded(report: CheckReport, name: str) -> Iterator[Check]:
    """One check's record, added to ``report`` as it starts: a FAIL (its detail set by :func:`run`) unless the
    block ends without raising, when it is a PASS."""
    check = Check(name, "fail", "")
    report.checks.append(check)
    yield check
    check.status = "pass"


def _manifest_check(check: Check, models: Path, allow_untrained: bool) -> tuple[dict, str, Preset]:
    """The manifest check (:func:`check_manifest`), its detail what the models are and were trained on, its
    warnings the tables a port needs that the manifest lacks; returns the manifest, its sha256 and its preset."""
    manifest, digest, preset = check_manifest(models, allow_untrained)
    training = sorted({str((e.get("training") or {}).get("data") or "unrecorded data")
                       for e in manifest["networks"].values()})
    check.detail = (f"{manifest.get('format', 'lowres3d-models/1')}, preset {preset.name}, "
                    f"{manifest.get('precision', 'fp32')}, weights {manifest.get('weights', 'unrecorded')}, "
                    f"trained on {', '.join(training)}")
    check.warnings = [f"{models / MANIFEST_NAME}: no '{table}' table: a runtime other than this one (a port) "
                      "reads the grid and constants there; export the models again to write it"
                      for table in ("bev_grid", "normalisation") if table not in manifest]
    return manifest, digest, preset


def _files_check(check: Check, models: Path, manifest: dict, digest: str) -> ModelIdentity:
    """The files check (:func:`check_files`), its detail each file's sha256 (its first 12 digits), its warnings
    the files the manifest does not list; returns the model's identity, which the checked files make good."""
    check.warnings = check_files(models, manifest)
    check.detail = ", ".join(f"{name} {entry['sha256'][:12]}…" for name, entry in manifest["files"].items())
    sized = all("bytes" in entry for entry in manifest["files"].values())  # older manifests list no sizes
    check.detail += ": sizes and sha256s as listed" if sized else ": sha256s as listed"
    return model_identity(models, manifest, digest)


def _load_detector(models: Path, config: CheckConfig) -> Detector:
    """The sessions check's first half: the Detector on ``config.provider``, which loads each graph and checks
    its inputs and outputs against the manifest's preset; CheckFailed saying why it would not load."""
    try:
        return Detector(models, providers=config.provider, trt_cache_dir=config.trt_cache_dir)
    except (ModelFileError, InputError) as exc:
        raise CheckFailed(str(exc)) from exc


def _sessions_check(check: Check, detector: Detector, models: Path, manifest: dict, preset: Preset) -> None:
    """The sessions check's second half, on the loaded ``detector``: the manifest it read is the one checked, its
    detail the provider each network runs on, its warnings the Detector's."""
    if detector.manifest != manifest:
        raise CheckFailed(f"{models}: the manifest changed during the check (a copy in progress?)")
    check.warnings = list(detector.load_warnings)
    check.detail = (", ".join(f"{name} on {providers[0]}" for name, providers in detector.providers_in_use.items())
                    + f"; graph inputs match preset {preset.name}")


def _frame_check(check: Check, detector: Detector, frame: Frame, config: CheckConfig) -> None:
    """The frame check (:func:`check_frame`) on ``frame``'s scan read as :func:`frame_scan` says; any error of the
    run a CheckFailed naming it. InputError (not a failure: exit 2) for a scan the check cannot use as asked."""
    # Outside the try below: a frame the check cannot use as asked is no failure of the model (exit 2).
    scan_file = frame_folder(config) / "velodyne" / f"{frame.frame_id}.bin"
    points, scan = frame_scan(detector, frame.points, config.emulate_beams, scan_file)
    try:
        check.detail = check_frame(detector, frame, points, scan)
    except CheckFailed:
        raise
    except Exception as exc:  # an input error, or ONNX Runtime failing at its first run: a FAIL, not a traceback
        raise CheckFailed(f"the frame did not run ({type(exc).__name__}: {exc})") from exc


def run(config: CheckConfig) -> CheckReport:
    """Every check on ``config.models``, stopping at the first that fails (the rest reported as skipped).

    InputError for what is not the directory's fault: no such folder, a frame that cannot be read (or whose scan
    is thinned to lines other than the model's), a provider this ONNX Runtime build does not offer."""
    models = Path(config.models)
    if not models.is_dir():
        raise InputError(f"--models {models}: {'not a folder' if models.exists() else 'no such folder'}")
    frame = read_frame(config)  # before the checks: a bad --data is the command line's fault
    resolve_providers(config.provider)  # so is a provider this ONNX Runtime build does not offer at all
    report = CheckReport(models=str(models), checks=[])
    detector: Detector | None = None
    try:  # the checks in CHECKS' order, each needing what the ones before it found
        with _recorded(report, "manifest") as check:
            manifest, digest, preset = _manifest_check(check, models, config.allow_untrained)
        with _recorded(report, "files") as check:
            report.identity = _files_check(check, models, manifest, digest)
        with _recorded(report, "sessions") as check:
            detector = _load_detector(models, config)
            _sessions_check(check, detector, models, manifest, preset)
        with _recorded(report, "frame") as check:
            _frame_check(check, detector, frame, config)
    except CheckFailed as exc:
        report.checks[-1].detail = str(exc)
    finally:
        if detector is not None:
            detector.close()
    done = {check.name for check in report.checks}
    report.checks += [Check(name, "skip", "an earlier check failed") for name in CHECKS if name not in done]
    return report


def render(report: CheckReport) -> str:
    """The report as the command prints it: a line per check, its warnings under it, then the verdict."""
    lines = [f"{check.status.upper():4} {check.name:8} {check.detail}" + "".join(
        f"\n     warning: {warning}" for warning in check.warnings) for check in report.checks]
    if report.passed:
        assert report.identity is not None
        lines.append(f"passed: {report.models} is fit to ship; model id {report.identity.id}")
    else:
        failed = next(check for check in report.checks if check.status == "fail")
        lines.append(f"failed: {report.models}: the {failed.name} check; do not ship it")
    return "\n".join(lines)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    description = "\n\n".join(part for part in __doc__.split("\n\n") if not part.startswith("examples:"))
    parser = argparse.ArgumentParser(allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
                                     prog="python -m pipeline.check_models", description=description,
                                     formatter_class=HelpFormatter, epilog=examples(
                                         "python -m pipeline.check_models --models /srv/lowres3d/edge-v7",
                                         "python -m pipeline.check_models --models DIR --provider tensorrt "
                                         "--json check.json",
                                         "python -m pipeline.check_models --models DIR --provider tensorrt "
                                         "--trt-cache-dir /var/cache/lowres3d/tensorrt"))
    parser.add_argument("--models", type=Path, required=True, metavar="DIR", help="the model directory to check")
    parser.add_argument("--provider", choices=("cpu", "cuda", "tensorrt"),
                        help="the execution provider the vehicles run (default: the best this ONNX Runtime offers)")
    parser.add_argument("--data", type=Path, metavar="DIR",
                        help="a KITTI object folder to take the frame from (default: the checkout's tests/data)")
    parser.add_argument("--frame", default=SAMPLE_FRAME, metavar="ID",
                        help=f"its frame id, or its number (6 for 000006; default {SAMPLE_FRAME})")
    parser.add_argument("--emulate-beams", type=int, choices=(0, *BEAM_COUNTS), metavar="N",
                        help="thin the scan to N lines first, 0 to run it as stored (default: the model's own line "
                             "count; a scan with that count already runs as stored)")
    parser.add_argument("--allow-untrained", action="store_true",
                        help="pass a directory exported without trained weights (latency tests; never a vehicle)")
    parser.add_argument("--trt-cache-dir", type=Path, metavar="DIR",
                        help="with --provider tensorrt, where TensorRT's engines are built and kept, as the "
                             "service's flag: give the service's cache to build its engines ahead of its first "
                             "frame (default: MODELS/trt_cache)")
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the report as JSON")
    return parser.parse_args(argv)


@quiet_interrupt("nothing was written; the model directory is as it was")
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        if args.json is not None:
            check_output(args.json, "--json")
            # Not over what the checks read: a --json named as the manifest replaced it, and then said "passed".
            check_not_input(args.json, "--json", {"--models": args.models,
                                                 "--data": SAMPLE_DIR if args.data is None else args.data})
        report = run(CheckConfig(models=args.models, provider=args.provider, data=args.data, frame=args.frame,
                                 emulate_beams=args.emulate_beams, allow_untrained=args.allow_untrained,
                                 trt_cache_dir=args.trt_cache_dir))
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(render(report))
    if args.json is not None:
        try:
            write_text_file(args.json, json.dumps(report.to_dict(), indent=2) + "\n")
        except OSError as exc:
            print(f"error: --json {args.json}: {exc.strerror or exc}", file=sys.stderr)
            return 2
    return 0 if report.passed else 1


if __name__ == "__main__":
    raise SystemExit(main())
