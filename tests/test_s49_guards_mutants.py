"""Edge values of today's pure-function guards, each pinning a mutant the older tests let through (the s49
mutation audit): an off-by-one or a dropped bound here would pass every other test and fail in service."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import service.settings as settings_module
from evaluation.depth_metrics import box_in_view
from pipeline.calib import Calibration, crop_calibration, depth_crop
from pipeline.errors import InputError
from pipeline.preprocess import scale_calibration
from pipeline.presets import check_preset, get_preset
from service.settings import DEFAULT_SOCKET_LIMIT, FD_RESERVE, Settings

ROOT = Path(__file__).resolve().parents[1]


def _with_file_limit(soft: int, code: str) -> list[str]:
    """Run ``code`` in a child whose soft open-file limit is ``soft``; its printed lines."""
    child = ("import resource\n"
             f"resource.setrlimit(resource.RLIMIT_NOFILE, ({soft}, resource.getrlimit(resource.RLIMIT_NOFILE)[1]))\n"
             + code)
    done = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, timeout=120, check=True,
                          cwd=ROOT)
    return done.stdout.splitlines()


def test_socket_cap_edges_under_a_low_open_file_limit() -> None:
    """At ulimit -n 100 (room 36): a queue whose admitted requests (1 + 50 + 16 = 67) outgrow the room still
    gets one socket more than that, so a client over the limit is told 503; and exactly 36 connections, the
    open-file limit less the reserve, are accepted (37 is refused, tests/test_service_connections_s49.py)."""
    lines = _with_file_limit(100, "from service.settings import Settings\n"
                                  "big = Settings(workers=1, queue_size=50)\n"
                                  "print(big.connection_limit(), big.socket_limit())\n"
                                  "print(Settings(workers=1, queue_size=2, max_connections=36).socket_limit())\n")
    assert lines == ["67 68", "36"]


@pytest.mark.parametrize(("files", "expected"), [(10_000, DEFAULT_SOCKET_LIMIT),
                                                 (DEFAULT_SOCKET_LIMIT + FD_RESERVE + 1, DEFAULT_SOCKET_LIMIT),
                                                 (None, DEFAULT_SOCKET_LIMIT)],
                         ids=["high limit", "just over", "unlimited"])
def test_socket_cap_default_is_at_most_the_default_limit(monkeypatch: pytest.MonkeyPatch, files: int | None,
                                                         expected: int) -> None:
    """However high ulimit -n is (or unlimited), the default cap stays DEFAULT_SOCKET_LIMIT. The limit is set by
    replacing its reader: raising the real soft limit past 4160 needs a hard limit some machines do not have."""
    monkeypatch.setattr(settings_module, "open_file_limit", lambda: files)
    assert Settings(workers=1, queue_size=2).socket_limit() == expected


def test_any_connection_count_above_the_requests_starts_where_the_open_file_limit_is_unlimited(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Unlimited (or unknown) ulimit -n bounds nothing: a cap far past DEFAULT_SOCKET_LIMIT is the operator's."""
    monkeypatch.setattr(settings_module, "open_file_limit", lambda: None)
    assert Settings(workers=1, queue_size=2, max_connections=100_000).socket_limit() == 100_000


def test_open_file_limit_reads_an_unlimited_soft_limit_as_none(monkeypatch: pytest.MonkeyPatch) -> None:
    """``ulimit -n unlimited`` (RLIM_INFINITY) is no number of files: open_file_limit says None, and the socket cap
    falls back to DEFAULT_SOCKET_LIMIT while any max_connections starts. The tests above replace open_file_limit
    itself; here only ``resource.getrlimit`` is, because Linux will not set an unlimited open-file limit for real
    (the soft limit cannot pass fs.nr_open, not even for root: setrlimit refuses RLIM_INFINITY)."""
    import resource

    monkeypatch.setattr(resource, "getrlimit", lambda which: (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
    assert settings_module.open_file_limit() is None
    assert Settings(workers=1, queue_size=2).socket_limit() == DEFAULT_SOCKET_LIMIT
    assert Settings(workers=1, queue_size=2, max_connections=100_000).socket_limit() == 100_000


def test_socket_cap_under_a_high_open_file_limit_set_for_real() -> None:
    """A soft ulimit -n of 10 000 (or this machine's hard limit, if lower), set in a child: open_file_limit reads
    it, and the default cap is the limit less FD_RESERVE, at most DEFAULT_SOCKET_LIMIT (4096 wherever the hard
    limit reaches 4161; here it is 20 000)."""
    import resource

    hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
    soft = 10_000 if hard == resource.RLIM_INFINITY else min(10_000, hard)
    lines = _with_file_limit(soft, "from service.settings import Settings, open_file_limit\n"
                                   "print(open_file_limit(), Settings(workers=1, queue_size=2).socket_limit())\n")
    assert lines == [f"{soft} {min(soft - FD_RESERVE, DEFAULT_SOCKET_LIMIT)}"]


@pytest.mark.parametrize("scale", [0.5, 1.0, 0.25])
def test_box_in_view_lands_where_the_network_calibration_projects(scale: float) -> None:
    """A box's corners in the network's view are where the calibration the pipeline hands the network
    (cropped, then resized: pipeline.preprocess) projects the points seen at them in the camera image; a
    misplaced half-pixel offset would shift every car's pixels off the car the detector sees."""
    calib = Calibration(P2=np.array([[720.0, 0.0, 610.0, 45.0], [0.0, 720.0, 175.0, -0.3], [0.0, 0.0, 1.0, 0.005]]),
                        R0_rect=np.eye(3), Tr_velo_to_cam=np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0],
                                                                    [1.0, 0.0, 0.0, 0.0]]))
    crop = depth_crop((375, 1242), 352, 1216)
    corners = np.array([[-2.0, 0.5, 12.0], [1.5, 1.6, 12.0]])  # rectified camera frame: top-left, bottom-right
    (left, top), (right, bottom) = calib.rect_to_image(corners)[0]
    view = scale_calibration(crop_calibration(calib, crop), scale)
    (v_left, v_top), (v_right, v_bottom) = view.rect_to_image(corners)[0]
    assert box_in_view((left, top, right, bottom), crop, scale) == pytest.approx((v_left, v_top, v_right, v_bottom))


def test_export_folder_stays_one_numbered_component() -> None:
    """A preset named ``..`` (any text is a name) still exports into a folder inside the scratch folder, and two
    presets of one name (a file reusing a built-in's) into two folders: the index keeps both apart."""
    from benchmarks.network_latency import export_folder

    dots = replace(get_preset("tiny"), name="..")
    assert export_folder(0, dots) not in {".", ".."}
    assert Path(export_folder(0, dots)).name == export_folder(0, dots)
    assert export_folder(0, get_preset("tiny")) != export_folder(1, get_preset("tiny"))


def test_check_models_preset_names_the_held_preset_when_the_names_differ(tmp_path: Path) -> None:
    """Another preset's name is said as such ("holds tiny models"), not as a field-by-field difference."""
    from benchmarks.latency import check_models_preset

    with pytest.raises(InputError) as refused:
        check_models_preset("edge", get_preset("tiny"), tmp_path)
    assert str(refused.value) == f"--preset edge: {tmp_path} holds tiny models (leave --preset out with --models)"


def test_a_non_positive_fpn_width_is_refused_wherever_it_stands() -> None:
    """Each of the per-level FPN widths is checked, not only the first: (96, 0, 196) is refused naming them."""
    paper = get_preset("paper")
    bad = replace(paper, pixor=replace(paper.pixor, fpn_channels=(96, 0, 196)))
    with pytest.raises(ValueError, match=r"pixor\.fpn_channels \[96, 0, 196\] must be positive"):
        check_preset(bad)
