"""What the model-directory tools and the command-line helpers promise, pinned where a mutation audit
found that no other test would notice a change.

Each test here was seen to fail on one or more mutants of pipeline/check_models.py, pipeline/cli.py,
pipeline/graph_inputs.py, pipeline/provenance.py, export/manifest.py, export/directory.py, export/parity.py or
the detect command's result lines (pipeline/detect.py, pipeline/kitti.py), and to pass on the real code: the bench
check's edges (the five bad files it names, a frame's scores just outside [0, 1], a depth net answering NaN, the
scan thinned to the model's lines), the argument types' boundaries, the channel pieces a lowered PIXOR is fed, the
git facts written into manifests, the model directory swapped in whole, the parity tolerances, and the exact
characters of a KITTI result line. The model directories are copies of the shipped ones (weights/ is only read),
altered in tmp_path; every network runs in ONNX Runtime.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import helper, numpy_helper

from pipeline.check_models import CheckConfig, CheckFailed, _finite, main, run
from pipeline.model_files import sha256_file
from tests.conftest import KITTI
from tests.test_provenance import _git, checkout  # noqa: F401 (checkout: test_provenance's fixture, used by name)
from tests.test_rollout import copy_models, edit_manifest

REPO = Path(__file__).resolve().parents[1]
WEIGHTS = REPO / "weights"


def save_graph(models: Path, name: str, graph: onnx.ModelProto) -> None:
    """Write ``graph`` as ``models/name`` and list its new sha256 and size, as an export of it would."""
    onnx.save(graph, str(models / name))
    entry = {"sha256": sha256_file(models / name), "bytes": (models / name).stat().st_size}
    edit_manifest(models, lambda m: m["files"].update({name: entry}))


@pytest.fixture
def models(tmp_path: Path) -> Path:
    """PIXOR alone (16 lines, 1.4 MB): the cheapest shipped directory to check."""
    return copy_models("edge-lidar16", tmp_path / "edge-lidar16")


# --------------------------------------------------------------------------- python -m pipeline.check_models
def test_a_manifest_listing_no_pixor_fails_the_manifest_check(models: Path) -> None:
    """Said at the manifest check, before any file is hashed or graph loaded, in words naming what is missing."""
    edit_manifest(models, lambda m: m["networks"].update(refine=m["networks"].pop("pixor")))
    report = run(CheckConfig(models=models, provider="cpu"))
    assert [c.status for c in report.checks] == ["fail", "skip", "skip", "skip"]
    assert report.checks[0].detail == f"{models / 'manifest.json'}: no 'pixor' network listed"


@pytest.mark.parametrize(("missing", "ends"), [(5, "f4.bin: model file listed in the manifest is missing"),
                                               (6, "f4.bin: model file listed in the manifest is missing; and 1 more")])
def test_the_files_check_names_five_bad_files_then_counts_the_rest(missing: int, ends: str, models: Path) -> None:
    edit_manifest(models, lambda m: m["files"].update({f"f{k}.bin": {"sha256": "0" * 64} for k in range(missing)}))
    detail = run(CheckConfig(models=models, provider="cpu")).checks[1].detail
    assert detail.count("model file listed in the manifest is missing") == 5, detail
    assert detail.endswith(f"{models / ends}"), detail


def test_sizes_are_claimed_checked_only_when_every_file_lists_one(models: Path) -> None:
    """An older manifest lists sha256s alone; one file without its size must not make the line claim sizes."""
    assert run(CheckConfig(models=models, provider="cpu")).checks[1].detail.endswith(": sizes and sha256s as listed")
    (models / "notes.txt").write_text("trained on runs/s20\n")
    edit_manifest(models, lambda m: m["files"].update({"notes.txt": {"sha256": sha256_file(models / "notes.txt")}}))
    files = run(CheckConfig(models=models, provider="cpu")).checks[1]
    assert files.status == "pass" and files.detail.endswith("…: sha256s as listed"), files.detail


def test_a_tensorrt_cache_is_no_stray_file_but_anything_else_unlisted_is(models: Path) -> None:
    """trt_cache/ is what the service builds beside the graphs; any other unlisted file says the copy was not clean."""
    (models / "trt_cache").mkdir()
    assert run(CheckConfig(models=models, provider="cpu")).checks[1].warnings == []
    (models / "pixor.onnx.old").write_bytes(b"x")
    assert run(CheckConfig(models=models, provider="cpu")).checks[1].warnings == [
        f"{models / 'pixor.onnx.old'}: not listed in the manifest (never loaded)"]


def test_the_bundled_scan_is_thinned_to_the_models_lines_unless_0_is_asked(models: Path, capsys) -> None:
    """A 16-line model is checked on the 64-line frame thinned to 16 lines, as the vehicles' scans are."""
    assert "frame 000006 (scan thinned to 16 lines): " in run(CheckConfig(models=models, provider="cpu")).checks[3].detail
    assert main(["--models", str(models), "--provider", "cpu", "--emulate-beams", "0"]) == 0
    assert "PASS frame    frame 000006 (scan as stored): " in capsys.readouterr().out


def test_an_output_of_another_shape_or_with_an_infinity_is_named() -> None:
    with pytest.raises(CheckFailed, match=r"^pixor.onnx output score: shape \[1, 1, 4\], where the preset gives "
                                          r"\[1, 1, 5\]$"):
        _finite("pixor.onnx output score", np.zeros((1, 1, 4), np.float32), (1, 1, 5))
    with pytest.raises(CheckFailed, match=r"^boxes: 1 of 6 values are NaN or infinite$"):
        _finite("boxes", np.array([0, 1, 2, np.inf, 4, 5], np.float32))


@pytest.mark.parametrize(("scale", "shift"), [(2.0, 0.0), (1.0, -0.5)])
def test_scores_just_outside_0_1_fail_the_frame_check(scale: float, shift: float, models: Path) -> None:
    """A graph whose score is not a probability (a head exported without its sigmoid, or rescaled): each edge on
    its own, scores above 1 but none below 0 (x 2), and below 0 but none above 1 (- 0.5)."""
    graph = onnx.load(str(models / "pixor.onnx"))
    sigmoid = next(node for node in graph.graph.node if list(node.output) == ["score"])
    sigmoid.output[0] = "score_probability"
    graph.graph.initializer.extend([numpy_helper.from_array(np.array(scale, np.float32), "score_scale"),
                                    numpy_helper.from_array(np.array(shift, np.float32), "score_shift")])
    graph.graph.node.extend([helper.make_node("Mul", ["score_probability", "score_scale"], ["score_scaled"]),
                             helper.make_node("Add", ["score_scaled", "score_shift"], ["score"])])
    save_graph(models, "pixor.onnx", graph)
    report = run(CheckConfig(models=models, provider="cpu"))
    assert [c.status for c in report.checks] == ["pass", "pass", "pass", "fail"]
    found = re.fullmatch(r"pixor.onnx output score: values from (\S+) to (\S+), not in \[0, 1\]", report.checks[3].detail)
    assert found, report.checks[3].detail
    low, high = float(found[1]), float(found[2])
    assert (low >= 0 and high > 1) if shift == 0 else (low < 0 and high <= 1), (low, high)


def test_a_depth_net_answering_nan_fails_the_frame_check(tmp_path: Path) -> None:
    """NaN depth makes no pseudo point (the voxelizer drops it), so PIXOR and the boxes alone would pass as a
    LiDAR-only run: the depth map is checked itself."""
    models = copy_models("edge", tmp_path / "edge")
    graph = onnx.load(str(models / "depth.onnx"))
    largest = max((t for t in graph.graph.initializer if t.data_type == onnx.TensorProto.FLOAT),
                  key=lambda t: int(np.prod(t.dims)))
    largest.CopyFrom(numpy_helper.from_array(np.full(tuple(largest.dims), np.nan, np.float32), largest.name))
    save_graph(models, "depth.onnx", graph)
    report = run(CheckConfig(models=models, provider="cpu"))
    assert [c.status for c in report.checks] == ["pass", "pass", "pass", "fail"]
    assert report.checks[3].detail.startswith("depth.onnx output depth: "), report.checks[3].detail
    assert "NaN or infinite" in report.checks[3].detail


def test_a_file_given_as_the_models_folder_is_the_command_lines_fault(tmp_path: Path) -> None:
    """Status 2 and one line, in a real run of the command: not a manifest check failing with status 1."""
    afile = tmp_path / "edge.tar"
    afile.write_bytes(b"not a folder")
    done = subprocess.run([sys.executable, "-m", "pipeline.check_models", "--models", str(afile)], cwd=REPO,
                          capture_output=True, text=True, timeout=60, check=False)
    assert (done.returncode, done.stdout, done.stderr) == (2, "", f"error: --models {afile}: not a folder\n")


def test_a_report_that_cannot_be_written_after_the_checks_is_status_2(models: Path, capsys) -> None:
    """--json /dev/full passes the check made before the run (a writable file) and fails at the write: status 2,
    not the run's 0, and the report already printed stays on stdout."""
    assert main(["--models", str(models), "--provider", "cpu", "--json", "/dev/full"]) == 2
    captured = capsys.readouterr()
    assert captured.out.splitlines()[-1].startswith(f"passed: {models} is fit to ship")
    assert captured.err == "error: --json /dev/full: No space left on device\n"


def test_an_untrained_directory_let_through_still_warns_under_sessions(models: Path, capsys) -> None:
    edit_manifest(models, lambda m: m["networks"]["pixor"].update(weights="initialised (untrained)"))
    assert main(["--models", str(models), "--provider", "cpu", "--allow-untrained"]) == 0
    out = capsys.readouterr().out.splitlines()
    sessions = out.index(next(line for line in out if line.startswith("PASS sessions ")))
    assert out[sessions + 1].startswith(f"     warning: {models}: pixor has initialised (untrained) weights"), out


# --------------------------------------------------------------------------- the commands' shared argument types
@pytest.mark.parametrize(("parse", "text", "value"), [
    ("positive_int", "1", 1), ("non_negative_int", "0", 0), ("positive_float", "1e-9", 1e-9),
    ("probability", "0", 0.0), ("probability", "1", 1.0), ("frame_rate", "0.1", 0.1), ("frame_rate", "1000", 1000.0),
    ("gpu_ids", "1,0", [1, 0]),
])
def test_each_argument_type_takes_its_bounds(parse: str, text: str, value: object) -> None:
    """The ends of each range are in it: --score-threshold 0 keeps every box, 1 only certain ones."""
    from pipeline import cli

    assert getattr(cli, parse)(text) == value


@pytest.mark.parametrize(("parse", "text", "says"), [
    ("positive_int", "0", "must be at least 1, got 0"), ("non_negative_int", "-1", "must be 0 or more, got -1"),
    ("positive_float", "0", "must be a positive number, got 0"),
    ("positive_float", "inf", "must be a positive number, got inf"),
    ("probability", "-0.001", "must be between 0 and 1, got -0.001"),
    ("probability", "1.001", "must be between 0 and 1, got 1.001"),
    ("frame_rate", "0.09", "must be from 0.1 to 1000 frames a second, got 0.09"),
    ("frame_rate", "1000.5", "must be from 0.1 to 1000 frames a second, got 1000.5"),
    ("gpu_ids", "0,1,0", "a GPU id given twice in '0,1,0'"),
])
def test_each_argument_type_refuses_just_past_its_bounds(parse: str, text: str, says: str) -> None:
    import argparse

    from pipeline import cli

    with pytest.raises(argparse.ArgumentTypeError) as refused:
        getattr(cli, parse)(text)
    assert str(refused.value) == says


def test_a_frame_list_named_in_digits_is_a_file_when_it_exists(tmp_path: Path, monkeypatch) -> None:
    """--frames 100 is the first 100 frames, unless a file called 100 is there: then it is that file's list."""
    from pipeline.cli import list_or_count

    monkeypatch.chdir(tmp_path)
    assert list_or_count("100") == 100
    Path("100").write_text("000006\n")
    assert list_or_count("100") == Path("100")


def test_an_output_file_given_a_folders_name_or_below_a_file_is_refused(tmp_path: Path) -> None:
    from pipeline.cli import check_output
    from pipeline.errors import InputError

    with pytest.raises(InputError, match=r"^--json .*: is a directory; give a file name$"):
        check_output(tmp_path, "--json")
    (tmp_path / "report").write_text("")
    with pytest.raises(InputError, match=r"^--json .*/report/new/check.json: .*/report is a file, not a directory$"):
        check_output(tmp_path / "report" / "new" / "check.json", "--json")
    check_output(tmp_path / "new" / "check.json", "--json")  # folders above are made when it is written


def test_an_output_inside_what_the_run_reads_is_refused_but_beside_the_data_folders_is_not(tmp_path: Path) -> None:
    """--models DIR is read whole; --data ROOT only in its KITTI folders, so ROOT/outputs may hold results."""
    from pipeline.cli import check_not_input
    from pipeline.errors import InputError

    models, data = tmp_path / "models", tmp_path / "kitti"
    with pytest.raises(InputError, match="would be written over what --models"):
        check_not_input(models / "cache" / "x", "--out", {"--models": models, "--data": data})
    with pytest.raises(InputError, match="would be written over what --data"):
        check_not_input(data / "velodyne" / "cache", "--out", {"--models": models, "--data": data})
    check_not_input(data / "outputs", "--out", {"--models": models, "--data": data})


@pytest.mark.parametrize(("count", "ends"), [(10, "f0, f1, f2, f3, f4, f5, f6, f7, f8, f9"),
                                             (11, "f0, f1, f2, f3, f4, f5, f6, f7, f8, f9 and 1 more")])
def test_the_skipped_summary_names_ten_then_counts(count: int, ends: str) -> None:
    from pipeline.cli import skipped_summary

    assert skipped_summary([f"f{k}" for k in range(count)], "frame", 300) == (
        f"{count} of 300 frame(s) skipped (each named above with its reason): {ends}")


def test_a_flag_spelled_twice_is_named_as_last_given() -> None:
    """argparse keeps the last value, so the error names the spelling that gave it."""
    from pipeline.cli import as_given

    assert as_given(["--emulate-beams", "16", "--beams", "32"], "--emulate-beams", "--beams") == "--beams"
    assert as_given(["--beams=16", "--emulate-beams", "32"], "--emulate-beams", "--beams") == "--emulate-beams"


def test_a_figure_name_is_judged_by_its_suffix_in_any_case(tmp_path: Path) -> None:
    from pipeline.cli import check_figure

    check_figure(tmp_path / "Curve.PNG", "--plot")


def test_ctrl_c_and_a_missing_extra_give_the_shells_statuses(capsys) -> None:
    """130 (128 + SIGINT) for Ctrl-C, 2 for a package the runtime install leaves out, as every usage error."""
    from pipeline.cli import interrupted, missing_extra

    assert interrupted("nothing written") == 130
    assert missing_extra("error: install torch").code == 2
    assert capsys.readouterr().err == "interrupted: nothing written\nerror: install torch\n"


# --------------------------------------------------------------------------- graph inputs in channel pieces
def test_the_pieces_fed_are_the_whole_tensors_channels_as_views() -> None:
    """What the shipped edge-lidar16 PIXOR reads: bev[0:16] and bev[16:19], each a view of the one BEV buffer."""
    from pipeline.graph_inputs import session_feeds

    bev = np.arange(1 * 19 * 4 * 3, dtype=np.float32).reshape(1, 19, 4, 3)
    feeds = session_feeds(["bev[16:19]", "bev[0:16]"], {"bev": bev})
    assert feeds["bev[0:16]"].shape == (1, 16, 4, 3) and feeds["bev[16:19]"].shape == (1, 3, 4, 3)
    assert np.array_equal(np.concatenate([feeds["bev[0:16]"], feeds["bev[16:19]"]], axis=1), bev)
    assert all(np.shares_memory(feed, bev) and feed.flags.c_contiguous for feed in feeds.values())
    with pytest.raises(KeyError, match=r"no array for the network input 'rgb\[0:3\]' \(given: bev\)"):
        session_feeds(["rgb[0:3]"], {"bev": bev})


@pytest.mark.parametrize(("ranges", "tile"), [
    ([(0, 16), (16, 19)], True), ([(1, 16), (16, 19)], False), ([(0, 16), (17, 19)], False),
    ([(0, 16), (15, 19)], False), ([(0, 0), (0, 19)], False), ([], False),
])
def test_channel_ranges_tile_only_from_0_without_gap_overlap_or_empty_piece(ranges, tile: bool) -> None:
    from pipeline.graph_inputs import tiles

    assert tiles(ranges) is tile


def test_pieces_join_back_into_the_whole_shape_in_channel_order() -> None:
    from pipeline.graph_inputs import whole_inputs, whole_shapes

    shapes = {"bev[16:19]": (1, 3, 100, 88), "bev[0:16]": (1, 16, 100, 88), "rgb": (1, 3, 8, 8)}
    assert whole_inputs(shapes) == {"bev": [(0, 16), (16, 19)]}
    assert whole_shapes(shapes) == {"bev": (1, 19, 100, 88), "rgb": (1, 3, 8, 8)}
    with pytest.raises(ValueError, match="do not match their channel ranges or each other"):
        whole_shapes({"bev[0:16]": (1, 15, 100, 88), "bev[16:19]": (1, 3, 100, 88)})
    with pytest.raises(ValueError, match="do not match their channel ranges or each other"):
        whole_shapes({"bev[0:16]": (1, 16, 100, 88), "bev[16:19]": (1, 3, 100, 87)})
    with pytest.raises(ValueError, match=r"the inputs bev\[0:16\], bev\[17:19\] do not cover the channels of 'bev'"):
        whole_shapes({"bev[0:16]": (1, 16, 100, 88), "bev[17:19]": (1, 2, 100, 88)})


# --------------------------------------------------------------------------- which code made a result
def test_a_git_that_hangs_or_is_missing_gives_no_commit_instead_of_stopping_the_run(tmp_path: Path,
                                                                                   monkeypatch) -> None:
    """A git stuck on a network file system is given up after GIT_TIMEOUT_S (here 0.3 s, a real sleeping git)."""
    from pipeline import provenance

    hanging = tmp_path / "bin"
    hanging.mkdir()
    (hanging / "git").write_text("#!/bin/sh\nexec /bin/sleep 5\n")
    (hanging / "git").chmod(0o755)
    monkeypatch.setattr(provenance, "GIT_TIMEOUT_S", 0.3)
    monkeypatch.setenv("PATH", str(hanging))
    assert provenance.code_version(REPO)["commit"] is None
    monkeypatch.setenv("PATH", str(tmp_path / "nothing"))
    assert provenance.code_version(REPO)["commit"] is None


def test_a_checkout_whose_status_fails_is_of_unknown_dirtiness_not_clean(checkout: Path) -> None:  # noqa: F811
    """A corrupt index: git still names the commit, but cannot say whether files differ, so dirty is None."""
    from pipeline.provenance import code_version

    (checkout / ".git" / "index").write_bytes(b"DIRC garbage")
    assert code_version(checkout) == {"lowres3d": code_version()["lowres3d"],
                                      "commit": _git(checkout, "rev-parse", "HEAD"), "dirty": None}


# --------------------------------------------------------------------------- the manifest
def test_weights_are_summed_up_as_trained_untrained_or_which_part() -> None:
    from export.manifest import UNTRAINED, weights_summary

    def entry(weights: str):
        from export.manifest import NetworkEntry

        return NetworkEntry("x.onnx", [], [], 0, 0, {}, weights, None)

    assert weights_summary({"depth": entry(UNTRAINED), "pixor": entry(UNTRAINED)}) == UNTRAINED
    assert weights_summary({"depth": entry("trained"), "pixor": entry("trained")}) == "trained"
    assert weights_summary({"depth": entry(UNTRAINED), "pixor": entry("trained")}) == (
        f"partially trained: depth {UNTRAINED}, pixor trained")


def test_graph_inputs_leave_out_weights_an_older_exporter_listed_as_inputs(tmp_path: Path) -> None:
    """ONNX IR < 4 listed every initializer among the graph's inputs too; a runtime feeds only the real ones."""
    from export.manifest import graph_inputs

    weight = numpy_helper.from_array(np.ones((2, 3), np.float32), "w")
    graph = helper.make_graph([helper.make_node("MatMul", ["x", "w"], ["y"])], "g",
                              [helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1, 2]),
                               helper.make_tensor_value_info("w", onnx.TensorProto.FLOAT, [2, 3])],
                              [helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1, 3])], [weight])
    onnx.save(helper.make_model(graph), str(tmp_path / "g.onnx"))
    assert graph_inputs(tmp_path / "g.onnx") == [{"name": "x", "shape": [1, 2]}]


def test_a_manifest_built_again_lists_what_the_shipped_export_wrote_and_verifies(models: Path) -> None:
    """build_manifest on the shipped edge-lidar16 files: the grid (nx across, ny along, as the voxelizer makes it)
    and each file's sha256 and size as the export that shipped them wrote; the runtime's verifier takes it."""
    from export.manifest import NetworkEntry, build_manifest, verify_model_dir, write_manifest
    from pipeline.presets import preset_from_dict

    shipped = json.loads((models / "manifest.json").read_text())
    pixor = shipped["networks"]["pixor"]
    entry = NetworkEntry("pixor.onnx", [], [], pixor["parameters"], pixor["flops"], pixor["flops_by_op"], "trained",
                         pixor["training"])
    built = build_manifest(preset_from_dict(shipped["preset_config"]), {"pixor": entry}, models, {}, {}, {})
    assert built["bev_grid"] == shipped["bev_grid"] and built["files"] == shipped["files"]
    write_manifest(models, built)
    assert verify_model_dir(models)["files"]["pixor.onnx"]["bytes"] == (models / "pixor.onnx").stat().st_size


def test_a_model_directory_with_a_changed_file_is_refused_by_its_verifier(models: Path) -> None:
    from export.manifest import verify_model_dir
    from pipeline.model_files import ModelFileError

    assert verify_model_dir(models)["preset"] == "edge"
    data = bytearray((models / "pixor.onnx").read_bytes())
    data[-1] ^= 1
    (models / "pixor.onnx").write_bytes(bytes(data))
    with pytest.raises(ModelFileError, match="pixor.onnx: sha256 mismatch"):
        verify_model_dir(models)


# --------------------------------------------------------------------------- writing a model directory
def test_an_empty_folder_or_the_same_models_directory_may_be_replaced_but_not_another(models: Path,
                                                                                      tmp_path: Path) -> None:
    from export.directory import check_destination
    from pipeline.model_files import ModelFileError

    (tmp_path / "empty").mkdir()
    check_destination(tmp_path / "empty", "edge", "fp32")
    check_destination(models, "edge", "fp32")  # a manifest without "precision" is fp32
    check_destination(models, "edge")  # precision not said: whatever the directory holds
    with pytest.raises(ModelFileError, match=r"holds a model of preset edge \(fp32\); this writes preset "
                                             r"edge \(int8\)"):
        check_destination(models, "edge", "int8")
    with pytest.raises(ModelFileError, match=r"holds a model of preset edge \(fp32\); this writes preset "
                                             r"tiny \(fp32\)"):
        check_destination(models, "tiny", "fp32")
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "a.txt").write_text("x")
    with pytest.raises(ModelFileError, match="exists and is not a model directory"):
        check_destination(tmp_path / "notes", "edge")


def test_a_staged_copy_takes_only_the_models_files_and_leaves_nothing_beside_it(models: Path, tmp_path: Path) -> None:
    from export.directory import staged

    (models / "trt_cache").mkdir()  # built for the source's graphs: not carried to a rewritten directory
    out = tmp_path / "out"
    (tmp_path / ".out.staging").mkdir()  # what a killed run left
    (tmp_path / ".out.staging" / "half.onnx").write_bytes(b"x")
    with staged(out, models) as folder:
        assert sorted(p.name for p in folder.iterdir()) == ["manifest.json", "pixor.onnx"]
    with staged(out, models) as folder:  # over the earlier out: swapped in whole, the old one removed
        (folder / "note.txt").write_text("second")
    assert (out / "note.txt").read_text() == "second"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["edge-lidar16", "out"]


def test_a_failure_while_staging_leaves_the_earlier_directory_and_no_staging_folder(models: Path,
                                                                                  tmp_path: Path) -> None:
    from export.directory import staged
    from pipeline.model_files import ModelFileError

    before = {p.name: p.read_bytes() for p in models.iterdir()}
    with pytest.raises(RuntimeError, match="parity"), staged(models, models) as folder:
        (folder / "pixor.onnx").write_bytes(b"half")
        raise RuntimeError("parity")
    assert {p.name: p.read_bytes() for p in models.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["edge-lidar16"]
    with pytest.raises(ModelFileError, match="lies inside the model directory"), staged(models / "v2", models):
        pass


# --------------------------------------------------------------------------- parity with PyTorch
class _Off:
    """A network whose outputs are the wrapped one's, changed by ``change``: a PyTorch side that disagrees with
    the ONNX file by a known amount."""

    def __init__(self, net, change) -> None:
        self.net, self.change = net, change

    def eval(self):
        self.net.eval()
        return self

    def __call__(self, *inputs):
        return self.change(self.net(*inputs))


def _shipped(directory: str, network: str):
    """The shipped network in PyTorch (its ONNX weights loaded), its ONNX Runtime session and a real frame's inputs."""
    from export.inputs import kitti_inputs
    from export.parity import cpu_session
    from models import build_network
    from models.onnx_weights import load_onnx_weights
    from pipeline.presets import preset_from_dict

    path = WEIGHTS / directory / f"{network}.onnx"
    preset = preset_from_dict(json.loads((path.parent / "manifest.json").read_text())["preset_config"])
    net = build_network(network, preset).eval()
    load_onnx_weights(net, path)
    return net, cpu_session(path), kitti_inputs(preset)


def test_depth_parity_is_relative_so_far_depths_may_differ_by_more_than_a_millimetre() -> None:
    """Depth within 0.05 % passes (4 cm at 80 m, far beyond 1e-3 m), within 0.2 % fails: the bound is relative."""
    from export.parity import depth_parity

    net, session, inputs = _shipped("edge", "depth")
    close = depth_parity(_Off(net, lambda d: d * 1.0005), session, inputs)
    assert close.passed and close.extra["max_abs_error_m"] > 2e-3, close
    assert not depth_parity(_Off(net, lambda d: d * 1.002), session, inputs).passed


def test_regression_parity_scales_with_the_maps_largest_value_and_every_failure_is_listed() -> None:
    """The trained regression reaches past 1, so its bound is 1e-3 of its largest value: an offset of half that
    passes, twice that fails, and require_parity then names both failing comparisons."""
    from export.parity import ParityError, pixor_parity, require_parity

    net, session, inputs = _shipped("edge-lidar16", "pixor")
    exact = pixor_parity(net, session, inputs)
    scale = exact[1].extra["max_abs_regression"]
    assert scale > 2 and all(r.passed for r in exact)
    assert all(r.passed for r in pixor_parity(_Off(net, lambda out: (out[0], out[1] + 5e-4 * scale)), session, inputs))
    off = pixor_parity(_Off(net, lambda out: (out[0] + 2e-4, out[1] + 2e-3 * scale)), session, inputs)
    assert [r.passed for r in off] == [False, False]
    with pytest.raises(ParityError) as refused:
        require_parity(exact + off)
    lines = str(refused.value).splitlines()
    assert lines[0] == "ONNX Runtime disagrees with PyTorch:" and len(lines) == 3
    assert lines[1].startswith("  pixor on KITTI") and "score max absolute error" in lines[1]
    assert "regression max absolute error" in lines[2]


def test_an_error_equal_to_its_tolerance_passes() -> None:
    from export.parity import ParityResult

    assert ParityResult("pixor", "x", "score max absolute error", 1e-4, 1e-4, {}).passed
    assert not ParityResult("pixor", "x", "score max absolute error", 1.0001e-4, 1e-4, {}).passed


# --------------------------------------------------------------------------- python -m pipeline.detect's result files
def _detect(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline.detect", "--models", str(WEIGHTS / "edge-lidar16"),
                           "--no-pictures", "--no-progress", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=120, check=False)


def test_result_lines_keep_kittis_field_order_and_decimals_and_a_skipped_frame_loses_its_old_file(
        tmp_path: Path) -> None:
    """Each line: type, truncated and the 2D box in 2 decimals, occluded a whole number, alpha, h w l, x y z and
    rotation_y in 4, the score in 4 (the devkit reads by position: l before h would be a car 4 m tall). The
    count the command prints is the lines written. A frame of a second run whose scan is cut off is skipped with
    status 1, and its result file from the first run is removed, not passed off as the second run's."""
    data = tmp_path / "kitti"
    for part, suffix in (("image_2", ".png"), ("velodyne", ".bin"), ("calib", ".txt")):
        (data / part).mkdir(parents=True)
        for fid in ("000003", "000006"):
            shutil.copy(KITTI / part / f"{fid}{suffix}", data / part / f"{fid}{suffix}")
    out = tmp_path / "out"
    done = _detect("--data", str(data), "--emulate-beams", "16", "--score-threshold", "0.05", "--out", str(out))
    assert done.returncode == 0, done.stderr
    rows = [row for fid in ("000003", "000006") for row in (out / "data" / f"{fid}.txt").read_text().splitlines()]
    assert len(rows) >= 3 and done.stdout.startswith(f"2 frame(s), {len(rows)} detection(s) → {out}/data\n")
    decimals = [2, 0, 4, 2, 2, 2, 2, 4, 4, 4, 4, 4, 4, 4, 4]
    for row in rows:
        fields = row.split()
        assert fields[0] == "Car" and len(fields) == 16, row
        assert [len(f.partition(".")[2]) for f in fields[1:]] == decimals, row
        height, width, length = map(float, fields[8:11])
        assert height < length and width < length, row
    scan = data / "velodyne" / "000003.bin"
    scan.write_bytes(scan.read_bytes()[:-6])  # cut off inside a point
    again = _detect("--data", str(data), "--emulate-beams", "16", "--out", str(out))
    assert again.returncode == 1, again.stderr
    assert f"removed its result file {out / 'data' / '000003.txt'}" in again.stderr
    assert sorted(p.name for p in (out / "data").iterdir()) == ["000006.txt"]
