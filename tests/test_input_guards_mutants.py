"""What the input and output guards of session 47 promise, pinned where a mutation audit (session 48) found that no
other test would notice a change.

Each test here was seen to fail on the mutant its docstring names (of pipeline/cli.py, pipeline/kitti.py,
pipeline/checks.py, service/middleware.py, models/run_checks.py) and to pass on the real code: an output folder
that is the input itself or is named relative to the working folder, Ctrl-C held only in a command's own main
thread and a second one ending it at once, JPEGs that start with no APPn marker, a big-endian scan's edges, the
early answer's lingering close bounded in bytes and in time as a whole, the frame lists' order, and the classes
line of an empty label folder.
"""

from __future__ import annotations

import asyncio
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.beams import check_scan_thinnable
from pipeline.checks import byte_order_hint
from pipeline.cli import check_not_input, check_not_inside, ctrl_c_held_while_loading
from pipeline.errors import InputError
from pipeline.kitti import parse_velodyne, read_velodyne
from service.inputs import _check_points
from service.middleware import Linger, send_early_error
from tests.conftest import KITTI
from tests.test_pipeline_mutants import _detect, _object_folder, _thinned

REPO = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------------------------- outputs and inputs
def test_an_output_folder_that_is_an_input_itself_is_refused(tmp_path: Path) -> None:
    """--out M --checkpoints M: replacing M deletes what the run reads, as for an input inside M.
    Mutant NI2 (only an input inside the folder refused)."""
    models = tmp_path / "models"
    models.mkdir()
    with pytest.raises(InputError, match=rf"^--out {models}: replacing it would delete --checkpoints {models},"):
        check_not_inside(models, "--out", {"--checkpoints": models})


def test_each_input_is_compared_past_one_not_given_or_not_there(tmp_path: Path) -> None:
    """An input not given (None) or not there does not end the comparison: the next one, inside --out, is refused;
    the one not there is left to its own check (it would delete nothing).
    Mutants NI1 (a missing input refused) and NI4 (the loop ends at the first input skipped)."""
    models = tmp_path / "models"
    frames = models / "kitti"
    frames.mkdir(parents=True)
    check_not_inside(models, "--out", {"--checkpoints": models / "run-not-there"})
    for skipped in (None, models / "run-not-there"):
        with pytest.raises(InputError, match=rf"replacing it would delete --data {frames},"):
            check_not_inside(models, "--out", {"--checkpoints": skipped, "--data": frames})


def test_paths_named_relative_to_the_working_folder_are_compared_as_the_same_files(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`--out models --data /abs/models/kitti` and `--out /abs/x --models x` name the same folders as their
    absolute spellings.
    Mutants NI5 (--out not resolved), IN7 (the output not resolved) and IN8 (the input not resolved)."""
    frames = tmp_path / "models" / "kitti"
    frames.mkdir(parents=True)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError, match="replacing it would delete --data"):
        check_not_inside(Path("models"), "--out", {"--data": frames})
    with pytest.raises(InputError, match="would be written over what --models"):
        check_not_input(Path("models/cache"), "--out", {"--models": tmp_path / "models"})
    with pytest.raises(InputError, match="would be written over what --models"):
        check_not_input(tmp_path / "models" / "cache", "--out", {"--models": Path("models")})


# What runs read under a --data root: the object layout's folders and split files, a drive's camera images and
# raw scans, the depth-completion maps and their ground truth (named here, not taken from pipeline.cli).
READ_FOLDERS = ("image_2", "velodyne", "calib", "label_2", "ImageSets", "image_02", "velodyne_raw", "depth_2",
                "groundtruth")


@pytest.mark.parametrize("folder", READ_FOLDERS)
def test_an_output_in_any_folder_a_data_root_is_read_from_is_refused(tmp_path: Path, folder: str) -> None:
    """Every folder of the object and depth-completion layouts (a drive's image_02, the maps' depth_2) is read by
    some run: an output in it is refused, beside them it is not.
    Mutants IN9 (image_02 dropped) and IN11 (depth_2 dropped)."""
    with pytest.raises(InputError, match=f"would be written over what --data {tmp_path}"):
        check_not_input(tmp_path / folder / "out", "--out", {"--data": tmp_path})
    check_not_input(tmp_path / "outputs", "--out", {"--data": tmp_path})


# ------------------------------------------------------------------------------------------ Ctrl-C while loading
def test_ctrl_c_is_held_only_for_a_command_in_its_main_thread() -> None:
    """An importer's Ctrl-C stays theirs (``command`` False), a thread's block touches no signal (Python allows
    handlers only in the main thread), and the command's own hold is taken down after its block.
    Mutants CC1 (``command`` ignored), CC8 (thread not checked: ValueError), CC5 (the hold left in place)."""
    before = signal.getsignal(signal.SIGINT)
    try:
        with ctrl_c_held_while_loading(False):
            assert signal.getsignal(signal.SIGINT) is before
        errors: list[BaseException] = []

        def in_a_thread() -> None:
            try:
                with ctrl_c_held_while_loading(True):
                    pass
            except BaseException as exc:  # noqa: BLE001 (what the thread met, for the main thread to assert)
                errors.append(exc)

        thread = threading.Thread(target=in_a_thread)
        thread.start()
        thread.join()
        assert errors == []
        with ctrl_c_held_while_loading(True):
            assert signal.getsignal(signal.SIGINT) is not before
        assert signal.getsignal(signal.SIGINT) is before
    finally:
        signal.signal(signal.SIGINT, before)


def _held(body: str) -> subprocess.CompletedProcess[str]:
    """Run ``body`` inside ctrl_c_held_while_loading(True) in a process of its own."""
    code = ("import os, signal\nfrom pipeline.cli import ctrl_c_held_while_loading\n"
            "with ctrl_c_held_while_loading(True):\n" + textwrap.indent(textwrap.dedent(body), "    ")
            + "print('after the block')\n")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=False,
                          cwd=REPO)


STOPPED = "interrupted: while the command was loading PyTorch and ONNX, before it began; nothing was written\n"


def test_a_second_ctrl_c_ends_the_command_at_once_even_inside_a_library_that_catches_everything() -> None:
    """The second Ctrl-C ends the process where it lands, though the library then loading catches every
    exception: nothing after it runs.
    Mutants CC3 (the second press only noted) and CC7 (sys.exit, whose SystemExit the library swallows)."""
    done = _held("""\
        try:
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGINT)
            print('went on')
        except BaseException:
            pass
    """)
    assert (done.returncode, done.stdout, done.stderr) == (130, "", STOPPED)


def test_a_keyboard_interrupt_raised_in_the_block_ends_in_the_same_one_line() -> None:
    """A KeyboardInterrupt raised by other means than the signal (a library's own) ends as the held Ctrl-C does:
    one line, status 130, no traceback. Mutant CC4 (not caught: a traceback)."""
    done = _held("raise KeyboardInterrupt\n")
    assert (done.returncode, done.stdout, done.stderr) == (130, "", STOPPED)


# ----------------------------------------------------------------------------- the early answer's lingering close
def _scope(**headers: str) -> dict:
    """An HTTP request's ASGI scope with ``headers`` (names with _ for -)."""
    return {"type": "http", "method": "POST", "path": "/v1/detect", "state": {"request_id": "r1"},
            "headers": [(name.replace("_", "-").encode(), value.encode()) for name, value in headers.items()]}


def _answer_early(scope: dict, receive, linger: Linger) -> tuple[list[dict], float]:
    """send_early_error's messages for ``scope`` (a 401 with Connection: close) and the seconds it took."""
    sent: list[dict] = []

    async def send(message: dict) -> None:
        sent.append(message)

    async def answer() -> None:
        await send_early_error(scope, receive, send, linger, 401, "unauthorized", "no token",
                               [(b"connection", b"close")])

    tic = time.monotonic()
    asyncio.run(asyncio.wait_for(answer(), 10))
    return sent, time.monotonic() - tic


def test_the_linger_is_the_receive_timeout_when_shorter_else_two_seconds() -> None:
    """No client is owed longer for its body than --receive-timeout-s, and none more than the 2 s a frame takes at
    12 Mbit/s (service/middleware.py); the byte bound is the body limit.
    Mutants LG1 (max: the longer), LG2 (LINGER_S 30 s) and LG3 (no bytes)."""
    assert Linger.of(3_000_000, 0.5) == Linger(max_bytes=3_000_000, timeout_s=0.5)
    assert Linger.of(3_000_000, 30.0) == Linger(max_bytes=3_000_000, timeout_s=2.0)


def test_a_body_past_the_byte_bound_is_not_read_on() -> None:
    """A client streaming more than the body limit is cut off once the limit is dropped, not read on until the
    time bound.
    Mutants LG4 (no byte bound), LG12 (the bytes not counted) and LG11 (the last empty part not sent)."""
    reads = 0

    async def endless() -> dict:
        nonlocal reads
        reads += 1
        await asyncio.sleep(0)
        return {"type": "http.request", "body": bytes(65536), "more_body": True}

    sent, took = _answer_early(_scope(content_length="100000000"), endless, Linger(max_bytes=200_000, timeout_s=2.0))
    assert reads == 4 and took < 1.0, (reads, took)  # 4 × 64 KiB: the first past 200,000 bytes
    assert sent[-1] == {"type": "http.response.body", "body": b"", "more_body": False}


def test_a_trickling_body_is_waited_for_at_most_the_linger_in_all() -> None:
    """The time bound is for the whole body, not for each of its parts: a client sending a few bytes every 50 ms
    is let go after the linger.
    Mutant LG5 (each part waited for the whole linger)."""
    async def trickle() -> dict:
        await asyncio.sleep(0.05)
        return {"type": "http.request", "body": b"x" * 10, "more_body": True}

    _, took = _answer_early(_scope(content_length="1000000"), trickle, Linger(max_bytes=2_000, timeout_s=0.3))
    assert 0.25 < took < 1.0, took


def test_the_connection_closes_as_soon_as_the_whole_body_is_read() -> None:
    """Once the body's last part is read the answer ends at once; the server's next receive() would only wait for
    the client to leave.
    Mutants LG7 (read on past the last part, until the linger's end) and LG11 (the last empty part not sent)."""
    parts = [{"type": "http.request", "body": b"x" * 10, "more_body": True},
             {"type": "http.request", "body": b"x" * 10, "more_body": False}]

    async def body_then_nothing() -> dict:
        if parts:
            return parts.pop(0)
        await asyncio.Event().wait()  # as uvicorn's receive() after the body, until the client leaves
        return {"type": "http.disconnect"}

    sent, took = _answer_early(_scope(content_length="20"), body_then_nothing, Linger(max_bytes=1_000, timeout_s=2.0))
    assert parts == [] and took < 0.5, took
    assert [m.get("more_body") for m in sent[1:]] == [True, False]


def test_a_client_waiting_for_100_continue_in_any_case_is_not_waited_for() -> None:
    """``Expect: 100-Continue`` is the same expectation (HTTP's tokens are case-insensitive): the client sends no
    body once answered, so the answer ends at once without a receive().
    Mutant LG9 (the case kept)."""
    async def no_body() -> dict:
        raise AssertionError("the body of a client waiting for 100 Continue was waited for")

    sent, _ = _answer_early(_scope(content_length="5000000", expect="100-Continue"), no_body,
                            Linger(max_bytes=10_000_000, timeout_s=2.0))
    assert [m["type"] for m in sent] == ["http.response.start", "http.response.body"]
    assert sent[0]["status"] == 401 and sent[1]["more_body"] is False


# ------------------------------------------------------------------------------------------- files that are no scan
def test_a_jpeg_without_an_app_segment_given_as_the_scan_is_named() -> None:
    """A JPEG may begin with its quantisation tables, no JFIF or Exif segment first (cv2's file with its APP0 cut
    out still decodes): named as a JPEG, not read as rows of 2 km.
    Mutant SK2 (APPn markers alone)."""
    encoded = cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))[1].tobytes()
    assert encoded[2:4] == b"\xff\xe0"
    bare = encoded[:2] + encoded[4 + int.from_bytes(encoded[4:6], "big"):]
    assert bare[2:4] == b"\xff\xdb" and cv2.imdecode(np.frombuffer(bare, np.uint8), cv2.IMREAD_COLOR).shape == (8, 8, 3)
    with pytest.raises(InputError, match=r"^scan\.bin: a JPEG image, not a KITTI scan"):
        parse_velodyne(bare + bytes(-len(bare) % 16), "scan.bin")


def test_points_written_as_text_with_tabs_and_crlf_are_named_as_text() -> None:
    """A scan written as text with tab-separated values and Windows line ends (whole rows in size) is named as
    text, not read as points.
    Mutant SK9 (tab and carriage return not taken for text)."""
    text = b"1.5\t2.5\t-1\t0.2\r\n" * 2
    assert len(text) % 16 == 0
    with pytest.raises(InputError, match=r"^scan\.bin: holds text \('1\.5"):
        parse_velodyne(text, "scan.bin")


# --------------------------------------------------------------------------------------------- a big-endian scan
def _plausible_scan() -> np.ndarray:
    """Rows a LiDAR gives: within 80 m, reflectance over all of [0, 1] (0 and 1 included)."""
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-80, 80, (500, 3)), rng.uniform(0, 1, 500)]).astype(np.float32)
    points[:2, 3] = (0.0, 1.0)
    return points


def test_a_big_endian_scan_with_reflectance_0_and_1_is_named_big_endian() -> None:
    """Reflectance 0 and 1 are KITTI's own edges: such a scan read in the wrong byte order still gets the
    big-endian hint.
    Mutants BO4 (0 excluded) and BO5 (1 excluded)."""
    misread = _plausible_scan().astype(">f4").view("<f4")
    assert "look big-endian" in byte_order_hint(misread)


def test_no_big_endian_hint_for_what_is_no_float32_scan_or_says_nothing_either_way() -> None:
    """An empty array, float64 rows (their bytes swap as 8-byte values) and an all-zero scan (the same bytes in
    either order) get no hint.
    Mutants BO2 (empty: ValueError), BO1 (float64 swapped: tiny values, plausible) and BO6 (extent 0 plausible)."""
    assert byte_order_hint(np.zeros((0, 4), np.float32)) == ""
    assert byte_order_hint(np.tile(np.array([10.0, 2.0, -1.0, 0.5]), (100, 1))) == ""
    assert byte_order_hint(np.zeros((100, 4), np.float32)) == ""


@pytest.mark.parametrize("marker", [*range(0xE0, 0xF0), 0xDB, 0xC4, 0xFE])
def test_every_marker_a_jpeg_may_open_with_is_named(marker: int) -> None:
    """A JPEG opens with SOI and then an APPn (FFE0–FFEF), a table (DQT FFDB, DHT FFC4) or a comment (FFFE)
    segment (ITU T.81, Table B.1): each is named as a JPEG.
    Mutant SK3 (APP15 left out)."""
    with pytest.raises(InputError, match=r"^scan\.bin: a JPEG image"):
        parse_velodyne(b"\xff\xd8\xff" + bytes([marker]) + bytes(60), "scan.bin")


def test_a_little_endian_scan_with_0_to_255_intensities_is_not_taken_for_big_endian() -> None:
    """Swapped, 0–255 intensities become tiny values in [0, 1], and coordinates finite ones of any size (here
    under 1,000 km): only the range bound (1 km) keeps such a scan, refused for its intensities, from the
    big-endian hint that would send its user to convert a file already right.
    Mutant BO7 (no range bound)."""
    rng = np.random.default_rng(1)
    points = np.column_stack([rng.uniform(-60, 60, (400, 3)), rng.integers(0, 256, 400)]).astype(np.float32)
    with np.errstate(over="ignore", invalid="ignore"):
        points = points[(np.abs(points.byteswap()) < 1e6).all(axis=1)]  # rows a swap leaves within 1,000 km
        assert np.abs(points.byteswap()[:, :3]).max() > 1000 and (points.byteswap()[:, 3] <= 1).all()
    assert byte_order_hint(points) == ""


def test_an_image_uploaded_as_the_scan_is_named_whatever_its_size() -> None:
    """The service names an image sent as ``points`` for what it is before it checks the size: a PNG of a size no
    multiple of 16 was told only that its size was wrong.
    Mutant SK7 (service/inputs.py's own check removed: the size check came first)."""
    png = cv2.imencode(".png", np.zeros((8, 8, 3), np.uint8))[1].tobytes()
    png += bytes(1 if len(png) % 16 == 0 else 0)  # not whole rows
    with pytest.raises(InputError, match=r"^points: a PNG image, not a KITTI scan"):
        _check_points(png, 1_000_000)


# ------------------------------------------------------------------------------ what a resumed run trains on (torch)
def _resume_check(started: tuple[list[str], list[str]], now: tuple[list[str], list[str]], tmp_path: Path) -> None:
    """check_same_frames for a run started on ``started`` (training, validation ids) resumed on ``now``."""
    from models.run_checks import check_same_frames, frame_fingerprints

    check_same_frames({"config": frame_fingerprints(*started)}, tmp_path, *now)


def test_a_resume_on_the_same_frames_in_another_order_or_split_otherwise_is_refused(tmp_path: Path) -> None:
    """The id list's order decides every batch (with the seed), and ids need not be of one width: frames 1, 23
    are not frames 12, 3.
    Mutants FS2 (the ids sorted first) and FS1 (joined without a separator)."""
    _resume_check((["000001", "000002"], ["000003"]), (["000001", "000002"], ["000003"]), tmp_path)
    for train in (["000002", "000001"], ["12", "3"]):
        started = ["000001", "000002"] if len(train[0]) == 6 else ["1", "23"]
        with pytest.raises(InputError, match=r"^--data / --train-split: .* was started on 2 training frames, and "
                                             r"the same flags now give 2 other frames"):
            _resume_check((started, ["000003"]), (train, ["000003"]), tmp_path)


def test_a_resume_on_other_validation_frames_is_refused_naming_the_validation_flags(tmp_path: Path) -> None:
    """Validation frames decide the best epoch: other ones are refused as the training frames are.
    Mutants FS4 (only the training frames compared), FS5 (named training frames) and FS8 (val recorded as train)."""
    with pytest.raises(InputError, match=r"^--val-data / --val-split: .* was started on 1 validation frame, and "
                                         r"the same flags now give 2 other frames"):
        _resume_check((["000001"], ["000003"]), (["000001"], ["000003", "000004"]), tmp_path)


def test_label_files_that_name_nothing_are_said_to_be_empty(tmp_path: Path) -> None:
    """Training labels that are all empty files: the refusal says so rather than naming an empty list of classes.
    Mutant CT2 (only "none")."""
    from models.run_checks import check_cars
    from tests.test_run_checks_mutants import _config
    from tests.test_run_checks_mutants import _object_folder as _labelled_folder

    data = _labelled_folder(tmp_path / "data", ("000003",))
    (data / "label_2" / "000003.txt").write_text("")
    with pytest.raises(InputError, match=r"\(classes found: none: the files are empty\); the detector learns"):
        check_cars(_config("detector", data), data, ["000003"], data, ["000003"])


def test_a_car_weight_below_1_with_no_car_to_weigh_is_refused_too(tmp_path: Path) -> None:
    """--car-weight 0.5 (the cars' pixels weighed less) weighs nothing without a Car, as 10 does.
    Mutant CA1 (only weights above 1 checked)."""
    from models.run_checks import check_cars
    from tests.test_run_checks_mutants import _config, _relabel
    from tests.test_run_checks_mutants import _object_folder as _labelled_folder

    data = _labelled_folder(tmp_path / "data", ("000003",))
    _relabel(data, "000003", "Vehicle")
    with pytest.raises(InputError, match=r"^--car-weight 0.5: no Car in the label_2 files"):
        check_cars(_config("depth", data, car_weight=0.5), data, ["000003"], data, ["000003"])


def test_a_pseudo_pixor_whose_preset_record_has_no_depth_section_loads(tmp_path: Path) -> None:
    """A checkpoint whose preset record is not a whole preset is compared on what it has: with no depth section
    there is no range to compare, and its PIXOR loads (the error's "up to {range:g} m" cannot be written without
    one).
    Mutant PR3 (a missing range compared: TypeError)."""
    from dataclasses import replace

    from models import build_pixor
    from models.checkpoint import load_checkpoint, load_network_weights, save_checkpoint
    from pipeline.presets import get_preset

    tiny = get_preset("tiny")
    path = save_checkpoint(tmp_path / "pixor.pt", tiny, {"pixor": build_pixor(tiny)}, {"task": "detector",
                                                                                       "input": "pseudo"})
    checkpoint = load_checkpoint(path)
    partial = {key: value for key, value in checkpoint.preset_config.items() if key != "depth"}
    load_network_weights(build_pixor(tiny), replace(checkpoint, preset_config=partial), "pixor", tiny)


def test_a_pixor_that_learned_on_farther_pseudo_points_is_refused_under_a_nearer_range(tmp_path: Path) -> None:
    """Either way round: a camera PIXOR trained under tiny (85 m) loaded under tiny-near35 would see its BEV hold
    none of the far points it learned on.
    Mutant PR5 (only a range longer than the training's refused)."""
    from models import build_pixor
    from models.checkpoint import load_checkpoint, load_network_weights, save_checkpoint
    from pipeline.presets import get_preset

    tiny, near = get_preset("tiny"), get_preset("tiny-near35")
    path = save_checkpoint(tmp_path / "pixor.pt", tiny, {"pixor": build_pixor(tiny)}, {"task": "joint"})
    with pytest.raises(ValueError, match=r"up to 85 m \(preset 'tiny'\); preset 'tiny-near35' keeps them up to 35 m"):
        load_network_weights(build_pixor(near), load_checkpoint(path), "pixor", near)


# --------------------------------------------------------------------------------------- scans that cannot be thinned
def test_the_refusal_names_the_lines_asked_for(tmp_path: Path) -> None:
    """--emulate-beams 32 on a 16-line sensor's scan: the line names the 32 given.
    Mutant TH1 (16 written)."""
    scan = tmp_path / "000003.bin"
    _thinned(shutil.copy(KITTI / "velodyne" / "000003.bin", scan))
    with pytest.raises(InputError, match=r"to evaluate scans of a 32-line sensor as they are, give --emulate-beams 0$"):
        check_scan_thinnable(scan, read_velodyne(scan).points, 32)


def test_an_empty_first_scan_is_left_to_its_frame_and_the_next_scan_decides(tmp_path: Path, capsys) -> None:
    """A first scan of no points is its frame's skip, as a cut-off one is: the next scan, a 16-line sensor's, is
    the one named.
    Mutant TH5 (the empty scan judged: "the scan has no points", advising --emulate-beams 0)."""
    data = _object_folder(tmp_path / "kitti")
    for scan in (data / "velodyne").glob("*.bin"):
        _thinned(scan)
    (data / "velodyne" / "000002.bin").write_bytes(b"")  # sorts first, reads as a scan of no points
    status, out, err = _detect(capsys, "--data", data, "--out", tmp_path / "out")
    assert (status, out) == (2, "")
    assert err.startswith(f"error: {data / 'velodyne' / '000003.bin'}: points: the scan has 16 rings"), err


def test_a_state_from_before_the_frame_record_is_not_compared(tmp_path: Path) -> None:
    """A run's state written before the frame lists were recorded (no sha256 in its config) resumes: there is
    nothing to compare it with.
    Mutant FS3 (a missing record taken for other frames)."""
    from models.run_checks import check_same_frames

    for state in ({"config": {"task": "detector"}}, {}):
        check_same_frames(state, tmp_path, ["000001"], ["000003"])


def test_a_run_with_its_own_validation_frames_resumes(tmp_path: Path) -> None:
    """Trained on one frame and validated on another, a run resumes on the same flags: each list's record is
    its own.
    Mutant FS7 (the lists recorded the other way round: every such run refused on --resume)."""
    from models.train import main
    from tests.test_train_cli import FRAME, args

    train, val = tmp_path / "train.txt", tmp_path / "val.txt"
    train.write_text(f"{FRAME}\n")
    val.write_text("000003\n")
    started = args("detector", tmp_path / "run", train, "--input", "lidar16", "--val-split", str(val))
    assert main(started) == 0
    assert main([*started, "--resume", "--epochs", "2"]) == 0
