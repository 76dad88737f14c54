"""A camera and a LiDAR that are not hardware-synchronised: the client sends each one's capture time with a frame
(query ``image_stamp_ns``, ``points_stamp_ns``: integer nanoseconds on one clock), gets them back with the
answer, and a frame whose image and scan lie far apart in time carries the warning ``sensor_skew``.

The library's check (pipeline.checks.sensor_skew) on numbers; the service in-process on the tiny exported models
of tests/test_service.py and a real KITTI frame (tests/data), and once as ``python -m service`` over a socket.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from pipeline.checks import (
    FRAME_WARNING_CODES,
    MAX_SENSOR_SKEW_MS,
    WARNING_MEANINGS,
    CodedWarning,
    WarningCode,
    check_stamp,
    coded,
    sensor_skew,
)
from pipeline.errors import InputError
from service.__main__ import settings_from_args
from tests.test_service import AppClient, assert_error, client, frame, parts, service, tiny_models  # noqa: F401
from tests.test_service_process import REPO, running_service

# A ROS stamp, sec 1718000000 and nanosec 1: above 2^53, so a float on the way would not give it back exactly.
SCAN_NS = 1_718_000_000 * 1_000_000_000 + 1
MS = 1_000_000  # nanoseconds
ROUTES = (("/v1/detect", {"format": "kitti"}), ("/v1/detect/bev.png", {}), ("/v1/detect/camera.png", {}))


def _stamps(image_ns: int | str | None = None, points_ns: int | str | None = None) -> dict[str, Any]:
    query: dict[str, Any] = {}
    if image_ns is not None:
        query["image_stamp_ns"] = image_ns
    if points_ns is not None:
        query["points_stamp_ns"] = points_ns
    return query


def _skew_warning(body: dict[str, Any]) -> str:
    """The one sensor_skew warning of a JSON answer (codes and texts are parallel lists)."""
    assert len(body["warnings"]) == len(body["warning_codes"]), body
    (index,) = [i for i, code in enumerate(body["warning_codes"]) if code == "sensor_skew"]
    return body["warnings"][index]


def _skew_count(app_client: AppClient) -> float:
    match = re.search(r'^lowres3d_frame_warnings_total\{code="sensor_skew"\} (\S+)$', app_client.get("/metrics").text,
                      re.MULTILINE)
    assert match, "no lowres3d_frame_warnings_total series for sensor_skew"
    return float(match.group(1))


# --------------------------------------------------------------------------- the library's check
def test_the_skew_warning_starts_past_the_threshold_and_says_which_came_first() -> None:
    """Up to the threshold nothing (to the nanosecond: stamps are ints, compared exactly); past it the skew in
    ms, which sensor was first, and what to do; a coded warning for ``Detections``-style lists."""
    limit = int(MAX_SENSOR_SKEW_MS * MS)
    assert sensor_skew(SCAN_NS + limit, SCAN_NS) is None and sensor_skew(SCAN_NS - limit, SCAN_NS) is None
    late = sensor_skew(SCAN_NS + limit + 1, SCAN_NS)
    assert late is not None and "captured 20.0 ms after the scan" in late and late.endswith("(+20.0 ms)")
    early = sensor_skew(SCAN_NS - 50 * MS, SCAN_NS)
    assert early is not None and "50.0 ms before the scan" in early and "(-50.0 ms)" in early
    assert sensor_skew(SCAN_NS + 50 * MS, SCAN_NS, max_skew_ms=60) is None
    assert coded((WarningCode.SENSOR_SKEW, late)) == [CodedWarning(WarningCode.SENSOR_SKEW, late)]


def test_stamps_on_two_clocks_are_named_as_such() -> None:
    """An image stamped since the epoch and a scan since the LiDAR's boot (or in microseconds) are seconds to
    years apart: the warning says the stamps are not one frame's, not that the frame is 50 years late."""
    since_boot = 3_600 * 1_000 * MS
    message = sensor_skew(SCAN_NS, since_boot)
    assert message is not None and "not one frame's capture times" in message and "two clocks" in message
    assert "1,717,996,400.000 s after" in message
    assert "not one frame's" in (sensor_skew(SCAN_NS, SCAN_NS // 1000) or "")  # microseconds for nanoseconds


@pytest.mark.parametrize(("stamp", "words"), [
    (1718000000.05, "got 1718000000.05"), (float("nan"), "got nan"), (-1, "-1 is negative"),
    (2**63, "more than int64 holds"), (True, "got a bool"), ("1718000000000000000", "got '1718000000000000000'"),
])
def test_a_stamp_that_is_not_integer_nanoseconds_is_refused_naming_the_argument(stamp: object, words: str) -> None:
    with pytest.raises(InputError) as raised:
        check_stamp(stamp, "image_stamp_ns")
    assert str(raised.value).startswith("image_stamp_ns: ") and words in str(raised.value), raised.value
    assert check_stamp(np.int64(SCAN_NS), "points_stamp_ns") == SCAN_NS  # a ROS bag's numpy column is fine
    assert check_stamp(0, "points_stamp_ns") == 0  # a simulator's clock starts at 0


def test_the_code_is_a_frame_code_with_a_meaning() -> None:
    """A frame's warning (so /metrics has its series and the schema lists it), explained for people."""
    assert WarningCode.SENSOR_SKEW in FRAME_WARNING_CODES and "sensor_skew" == f"{WarningCode.SENSOR_SKEW}"
    assert "in time" in WARNING_MEANINGS[WarningCode.SENSOR_SKEW]


# --------------------------------------------------------------------------- the service
def test_without_stamps_the_answer_is_what_it_was(client: AppClient, frame: dict[str, bytes]) -> None:  # noqa: F811
    """KITTI's frames are synchronised and their users send no stamps: no `stamps` key, no stamp header, no
    warning, whatever the route."""
    response = client.post("/v1/detect", params={"emulate_beams": 16}, files=parts(frame))
    assert response.status_code == 200, response.text
    body = response.json()
    assert set(body) == {"detections", "timings_ms", "model", "warnings", "warning_codes", "request_id"}
    assert body["warning_codes"] == ["beams_emulated"]
    for route, params in ((("/v1/detect", {}),) + ROUTES):
        answer = client.post(route, params={"emulate_beams": 16, **params}, files=parts(frame))
        assert answer.status_code == 200 and not any("stamp" in name for name in answer.headers), route


def test_the_stamps_come_back_exactly_and_close_ones_pass_quietly(client: AppClient, frame: dict[str, bytes]) -> None:  # noqa: F811
    """Within 20 ms: the stamps echoed to the nanosecond in the body and in headers on every route (KITTI lines
    and PNGs have no room in their body), the skew in ms, and no warning."""
    query = {"emulate_beams": 16, **_stamps(SCAN_NS + 12 * MS, SCAN_NS)}
    body = client.post("/v1/detect", params=query, files=parts(frame)).json()
    assert body["stamps"] == {"image_ns": SCAN_NS + 12 * MS, "points_ns": SCAN_NS, "skew_ms": 12.0}
    assert body["warning_codes"] == ["beams_emulated"]
    for route, params in ((("/v1/detect", {}),) + ROUTES):
        answer = client.post(route, params={**query, **params}, files=parts(frame))
        assert answer.status_code == 200, (route, answer.text)
        assert (answer.headers["x-image-stamp-ns"], answer.headers["x-points-stamp-ns"]) == (
            str(SCAN_NS + 12 * MS), str(SCAN_NS)), route
    # One stamp alone is echoed (a frame placed in time), with nothing to compare it with.
    alone = client.post("/v1/detect", params={"emulate_beams": 16, **_stamps(points_ns=SCAN_NS)}, files=parts(frame))
    assert alone.json()["stamps"] == {"image_ns": None, "points_ns": SCAN_NS, "skew_ms": None}
    assert "x-image-stamp-ns" not in alone.headers and alone.headers["x-points-stamp-ns"] == str(SCAN_NS)


def test_a_frame_whose_image_and_scan_are_apart_in_time_is_warned_and_counted(
    client: AppClient, frame: dict[str, bytes]  # noqa: F811
) -> None:
    """50 ms apart (1 m at 20 m/s): the coded warning with the skew, in the body and in X-Warning-Codes on every
    route, and counted in lowres3d_frame_warnings_total{code="sensor_skew"}."""
    before = _skew_count(client)
    query = {"emulate_beams": 16, **_stamps(SCAN_NS + 50 * MS, SCAN_NS)}
    body = client.post("/v1/detect", params=query, files=parts(frame)).json()
    message = _skew_warning(body)
    assert message.startswith("image and points: the image was captured 50.0 ms after the scan"), message
    assert body["stamps"]["skew_ms"] == 50.0
    for route, params in ROUTES:
        answer = client.post(route, params={**query, **params}, files=parts(frame))
        assert answer.status_code == 200, (route, answer.text)
        codes, warnings = json.loads(answer.headers["x-warning-codes"]), json.loads(answer.headers["x-warnings"])
        assert warnings[codes.index("sensor_skew")] == message, route
    assert _skew_count(client) == before + 1 + len(ROUTES)


def test_answers_out_of_order_are_placed_by_their_stamps(client: AppClient, frame: dict[str, bytes]) -> None:  # noqa: F811
    """Six frames sent at once (two workers, the rest queued) come back in any order; each answer carries its
    own frame's stamps and skew, and only the frames apart in time have the warning."""
    skews_ms = [0, 35, 5, -25, 19, 100]
    scans = [SCAN_NS + i * 100 * MS for i in range(len(skews_ms))]

    def send(i: int) -> dict[str, Any]:
        query = {"emulate_beams": 16, **_stamps(scans[i] + skews_ms[i] * MS, scans[i])}
        response = client.post("/v1/detect", params=query, files=parts(frame))
        assert response.status_code == 200, response.text
        return response.json()

    with ThreadPoolExecutor(len(skews_ms)) as pool:
        answers = list(pool.map(send, range(len(skews_ms))))
    for scan, skew, body in zip(scans, skews_ms, answers, strict=True):
        assert body["stamps"] == {"image_ns": scan + skew * MS, "points_ns": scan, "skew_ms": float(skew)}
        assert ("sensor_skew" in body["warning_codes"]) == (abs(skew) > MAX_SENSOR_SKEW_MS), (skew, body["warnings"])


@pytest.mark.parametrize(("query", "words"), [
    ({"image_stamp_ns": "1718000000.05"}, ["image_stamp_ns: expected an integer count of nanoseconds",
                                           "got 1718000000.05", "sec * 1000000000 + nanosec"]),
    ({"points_stamp_ns": "nan"}, ["points_stamp_ns: expected an integer", "got nan"]),
    ({"points_stamp_ns": "1.7e18"}, ["points_stamp_ns: expected an integer"]),
    ({"image_stamp_ns": "1.0"}, ["image_stamp_ns: expected an integer"]),  # pydantic alone would take it as 1
    ({"image_stamp_ns": "1_000"}, ["image_stamp_ns: expected an integer", "got '1_000'"]),  # and this as 1000
    ({"points_stamp_ns": "-5"}, ["points_stamp_ns: -5 is negative"]),
    ({"image_stamp_ns": str(2**63)}, ["image_stamp_ns: 9223372036854775808 is more than int64 holds"]),
    ({"image_stamp_ns": "9" * 5000}, ["image_stamp_ns: 5000 digits is more than int64 holds"]),
    ({"image_stamp_ns": "yesterday"}, ["image_stamp_ns: expected an integer", "got 'yesterday'"]),
    ({"image_stamp_ns": ""}, ["image_stamp_ns: expected an integer", "got ''"]),
    ({"image_stamp_ns": "1", "points_stamp_ns": "x"}, ["points_stamp_ns: expected an integer"]),
])
def test_a_stamp_in_another_form_is_a_422_naming_it(
    client: AppClient, frame: dict[str, bytes], query: dict[str, str], words: list[str]  # noqa: F811
) -> None:
    """One representation, integer nanoseconds: seconds as a float, NaN, a negative or out-of-range value are
    refused with one line naming the parameter and how to make nanoseconds, never rounded into a wrong stamp."""
    assert_error(client.post("/v1/detect", params=query, files=parts(frame)), 422, "invalid_input", *words)


def test_leading_zeros_do_not_count_as_digits_of_a_stamp() -> None:
    """A stamp padded with zeros is the number it spells (int() alone refuses 4,300 characters and more with a
    message about sys.set_int_max_str_digits); its significant digits are what int64 bounds."""
    from pydantic_core import PydanticCustomError

    from service.inputs import stamp_query

    assert stamp_query("0" * 5000 + "1718000000000000000") == 1718000000000000000
    with pytest.raises(PydanticCustomError, match="-5 is negative"):
        stamp_query("-" + "0" * 5000 + "5")
    with pytest.raises(PydanticCustomError, match="^20 digits is more than int64 holds"):
        stamp_query("0" * 10 + "9" * 20)


def test_the_threshold_is_a_setting_and_a_lidar_only_model_is_not_warned(
    tiny_models: Path, frame: dict[str, bytes], tmp_path: Path  # noqa: F811
) -> None:
    """--max-sensor-skew-ms moves the threshold. A LiDAR-only model's boxes come from the scan alone, so a late
    image changes nothing there; but its KITTI lines are placed in the image, and are warned. An image stamp
    without an image stamps nothing and is refused."""
    from tests.conftest import lidar_only_models

    query = {"emulate_beams": 16, **_stamps(SCAN_NS + 50 * MS, SCAN_NS)}
    with service(tiny_models, max_sensor_skew_ms=60.0) as relaxed:
        assert relaxed.post("/v1/detect", params=query, files=parts(frame)).json()["warning_codes"] == ["beams_emulated"]
        query_late = {**query, "image_stamp_ns": SCAN_NS + 61 * MS}
        assert "(more than 60 ms apart)" in _skew_warning(relaxed.post("/v1/detect", params=query_late,
                                                                       files=parts(frame)).json())
    with service(lidar_only_models(tiny_models, tmp_path / "lidar")) as lidar:
        body = lidar.post("/v1/detect", params=query, files=parts(frame)).json()
        assert body["warning_codes"] == ["beams_emulated"] and body["stamps"]["skew_ms"] == 50.0
        kitti = lidar.post("/v1/detect", params={**query, "format": "kitti"}, files=parts(frame))
        assert "sensor_skew" in json.loads(kitti.headers["x-warning-codes"])
        scan_alone = parts(frame, image=None, calib=None)
        assert lidar.post("/v1/detect", params=_stamps(points_ns=SCAN_NS), files=scan_alone).status_code == 200
        assert_error(lidar.post("/v1/detect", params=_stamps(SCAN_NS, SCAN_NS), files=scan_alone), 422,
                     "invalid_input", "image_stamp_ns: sent without an image part")


def test_the_schema_types_and_explains_the_stamps(client: AppClient) -> None:  # noqa: F811
    """A generated client gets int64 parameters that say their unit and clock, the echoed `stamps` (optional, so
    older answers still validate), the stamp headers on every route and the new code in warning_codes' list."""
    schema = client.get("/openapi.json").json()
    for route in ("/v1/detect", "/v1/detect/bev.png", "/v1/detect/camera.png"):
        operation = schema["paths"][route]["post"]
        parameters = {p["name"]: p for p in operation["parameters"] if p["in"] == "query"}
        for name in ("image_stamp_ns", "points_stamp_ns"):
            integer = parameters[name]["schema"]["anyOf"][0]
            assert integer == {"type": "integer", "format": "int64", "minimum": 0, "maximum": 2**63 - 1}, name
            assert "nanoseconds" in parameters[name]["description"], name
        headers = operation["responses"]["200"]["headers"]
        assert {"X-Image-Stamp-Ns", "X-Points-Stamp-Ns"} <= set(headers), route
    components = schema["components"]["schemas"]
    response = components["DetectResponse"]
    assert "stamps" not in response["required"] and "stamps" in response["properties"]
    assert "`sensor_skew` —" in response["properties"]["warning_codes"]["description"]
    assert set(components["SensorStamps"]["properties"]) == {"image_ns", "points_ns", "skew_ms"}
    assert "Unix epoch" in components["SensorStamps"]["properties"]["image_ns"]["description"]


@pytest.mark.parametrize(("value", "words"), [("0", "0.0: input should be greater than 0"),
                                              ("-5", "-5.0: input should be greater than 0"),
                                              ("nan", "nan: input should be a finite number")])
def test_a_threshold_that_is_not_a_positive_number_stops_the_start_naming_the_option(value: str, words: str) -> None:
    """As every setting: one line naming the option and its variable, exit status 2, no traceback."""
    assert settings_from_args(["--max-sensor-skew-ms", "35"]).max_sensor_skew_ms == 35.0
    run = subprocess.run([sys.executable, "-m", "service", "--max-sensor-skew-ms", value], check=False, cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and run.stderr.count("\n") == 1, run.stderr
    assert run.stderr == f"python -m service: --max-sensor-skew-ms (LOWRES3D_MAX_SENSOR_SKEW_MS) {words}\n"


def test_stamps_over_http(tiny_models: Path, frame: dict[str, bytes], tmp_path: Path) -> None:  # noqa: F811
    """``python -m service`` on 127.0.0.1 with the threshold in its environment: the echo, the warning and the
    refusal as a client on the vehicle's network sees them."""
    env = {"LOWRES3D_MAX_SENSOR_SKEW_MS": "30"}
    with running_service(tiny_models, tmp_path / "service.log", env=env) as server, \
            httpx.Client(base_url=server.url, timeout=30) as http:
        quiet = http.post("/v1/detect", params={"emulate_beams": 16, **_stamps(SCAN_NS + 25 * MS, SCAN_NS)},
                          files=parts(frame)).json()
        assert quiet["warning_codes"] == ["beams_emulated"] and quiet["stamps"]["image_ns"] == SCAN_NS + 25 * MS
        late = http.post("/v1/detect/bev.png", params={"emulate_beams": 16, **_stamps(SCAN_NS + 35 * MS, SCAN_NS)},
                         files=parts(frame))
        assert late.status_code == 200 and late.headers["x-image-stamp-ns"] == str(SCAN_NS + 35 * MS)
        warnings = dict(zip(json.loads(late.headers["x-warning-codes"]), json.loads(late.headers["x-warnings"]),
                            strict=True))
        assert "35.0 ms after the scan (more than 30 ms apart)" in warnings["sensor_skew"]
        assert_error(http.post("/v1/detect", params={"image_stamp_ns": "1718000000.035"}, files=parts(frame)),
                     422, "invalid_input", "image_stamp_ns: expected an integer count of nanoseconds")
