"""What a newcomer's read of service/ found (session 50): a pixel setting above what the decoder takes, the
pre-queue scan check without the file path's column hint, an error example the service never answers, and
error codes answered but not documented. The routes through the app over ASGI with the real tiny models and
KITTI frame 000006, as ``test_service.py``; each test failed on the code before its fix."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

import service
from pipeline.errors import InputError
from pipeline.kitti import MAX_IMAGE_PIXELS, parse_velodyne
from service.__main__ import settings_errors, settings_from_args
from service.errors import _HTTP_CODES
from service.middleware import CLIENT_CLOSED
from service.schemas import ERROR_CODES
from tests.test_service import AppClient, assert_error, client, frame, parts, tiny_models  # noqa: F401 - fixtures


# --------------------------------------------------------------------------- 1. --max-image-pixels' ceiling
def test_a_pixel_limit_above_the_decoders_stops_the_start_naming_the_ceiling(monkeypatch: pytest.MonkeyPatch) -> None:
    """An image the setting lets into the queue would be refused on its worker by the decoder's own limit
    (pipeline.kitti.MAX_IMAGE_PIXELS) as "a damaged header?": a setting above it is refused at start instead."""
    monkeypatch.setenv("LOWRES3D_MAX_IMAGE_PIXELS", str(MAX_IMAGE_PIXELS + 1))
    with pytest.raises(ValidationError) as caught:
        settings_from_args([])
    [line] = settings_errors(caught.value)
    assert line.startswith(f"--max-image-pixels (LOWRES3D_MAX_IMAGE_PIXELS) {MAX_IMAGE_PIXELS + 1}: "), line
    assert f"{MAX_IMAGE_PIXELS:,}" in line, line
    monkeypatch.setenv("LOWRES3D_MAX_IMAGE_PIXELS", str(MAX_IMAGE_PIXELS))  # the ceiling itself starts
    assert settings_from_args([]).max_image_pixels == MAX_IMAGE_PIXELS


# --------------------------------------------------------------------------- 2. a scan of 5 or 6 columns
@pytest.mark.parametrize("columns", [5, 6])
def test_a_scan_of_wider_rows_is_told_its_columns_before_the_queue(
    client: AppClient, frame: dict[str, bytes], columns: int  # noqa: F811
) -> None:
    """A driver's scan with a ring or time column, 101 rows (no whole number of 16-byte points): the service
    answers what reading the file answers, the column count and how to keep four, not only the size."""
    scan = np.zeros((101, columns), np.float32).tobytes()
    with pytest.raises(InputError) as read:
        parse_velodyne(scan, "points")
    error = assert_error(client.post("/v1/detect", files=parts(frame, points=scan)), 422, "invalid_input",
                         f"{columns}-column rows", f"reshape(-1, {columns})")
    assert error["message"] == str(read.value)


# --------------------------------------------------------------------------- 4. the documented example
def test_the_invalid_input_example_is_what_the_service_answers(client: AppClient, frame: dict[str, bytes]) -> None:  # noqa: F811
    """The OpenAPI example of a 422 is the service's own answer to a beam count it does not take."""
    detect = client.get("/openapi.json").json()["paths"]["/v1/detect"]["post"]
    example = detect["responses"]["422"]["content"]["application/json"]["examples"]["invalid_input"]
    answer = assert_error(client.post("/v1/detect", params={"emulate_beams": 15}, files=parts(frame)), 422,
                          "invalid_input")
    assert example["value"]["error"]["message"] == answer["message"]


# --------------------------------------------------------------------------- 5. the error codes
def _codes_in_source() -> set[tuple[int, str]]:
    """Each (status, code) pair the service's code writes (``ServiceError(503, "not_ready", …``,
    ``send_error(send, 413, "body_too_large", …``), read from its source."""
    pairs = set()
    for path in Path(service.__file__).parent.rglob("*.py"):
        pairs |= {(int(status), code) for status, code in re.findall(r"\b([45]\d\d),\s*\"([a-z_]+)\"", path.read_text())}
    return pairs


def test_every_code_the_service_answers_is_in_the_documented_table() -> None:
    """The framework's HTTP errors' codes (service.errors) and every pair the service writes are in ERROR_CODES,
    the table the OpenAPI document and docs/service.md give: 403 ``forbidden``, 406 ``not_acceptable`` and 503
    ``unavailable`` were mapped, never answered and never documented. 499 goes to no client (it left)."""
    written = _codes_in_source()
    assert {(503, "overloaded"), (413, "body_too_large"), (408, "request_timeout")} <= written  # the scan finds them
    answered = set(_HTTP_CODES.items()) | {(status, code) for status, code in written if status != CLIENT_CLOSED}
    undocumented = {(status, code) for status, code in answered if code not in ERROR_CODES.get(status, ())}
    assert not undocumented
