"""What a client sees of service/inputs.py, service/errors.py and service/schemas.py where no other test pinned it
(the mutation audit of session 46): which calibration a frame is detected with, and the status, code and field
named when a client's request is wrong.

Through the app over ASGI with the real tiny models and KITTI frame 000006, as ``test_service.py``.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from service.errors import validation_message
from tests.test_service import (  # noqa: F401 - fixtures
    FRAME,
    KITTI,
    AppClient,
    _chunk,
    _png_header,
    assert_error,
    client,
    frame,
    parts,
    service,
    tiny_models,
)

SCORE_ALL = {"score_threshold": 0.0}


def _moved_principal_point(calib: bytes) -> bytes:
    """The calibration with P2's principal point moved to the image's left edge (cx 10 px): a calibration for
    another camera, which the detector warns of."""
    lines = []
    for line in calib.decode().splitlines():
        if line.startswith("P2:"):
            values = line.split()[1:]
            values[2] = "10.0"  # row 0: fx 0 cx tx
            line = "P2: " + " ".join(values)
        lines.append(line)
    return ("\n".join(lines) + "\n").encode()


@pytest.fixture(scope="module")
def with_default(tiny_models: Path) -> Iterator[AppClient]:  # noqa: F811
    """The app with KITTI 000006's calibration as the server's default."""
    with service(tiny_models, default_calib=KITTI / "calib" / f"{FRAME}.txt") as app_client:
        yield app_client


def test_an_uploaded_calibration_is_used_over_the_servers_default(with_default: AppClient,
                                                                   frame: dict[str, bytes]) -> None:  # noqa: F811
    """The default is for frames sent without one: a rig that sends its own calibration is detected with it (here
    one whose principal point does not fit the image, which the answer warns of), never silently with the default."""
    own = with_default.post("/v1/detect", params=SCORE_ALL, files=parts(frame, calib=_moved_principal_point(frame["calib"])))
    assert own.status_code == 200, own.text
    assert any("P2's principal point (10.0, 181.5)" in w for w in own.json()["warnings"]), own.json()["warnings"]
    default = with_default.post("/v1/detect", params=SCORE_ALL, files=parts(frame, calib=None))
    assert default.status_code == 200 and default.json()["warnings"] == [], default.text


def test_a_bad_uploaded_calibration_is_refused_even_with_a_default(with_default: AppClient,
                                                                   frame: dict[str, bytes]) -> None:  # noqa: F811
    """A calibration the client sent and got wrong is its mistake to hear of, not one to paper over with the
    server's default."""
    response = with_default.post("/v1/detect", files=parts(frame, calib=b"P2: 1 2 3\n"))
    assert_error(response, 422, "invalid_input", "calib", "P2 needs 12 numbers")


def test_png_image_data_that_is_not_zlib_is_a_422_naming_the_image(client: AppClient,  # noqa: F811
                                                                   frame: dict[str, bytes]) -> None:  # noqa: F811
    """A PNG whose header and chunks are sound but whose image data is not a zlib stream: found only when it is
    inflated on a worker, still the client's mistake (not a 500)."""
    image = _png_header(1242, 375) + _chunk(b"IDAT", b"\x00\x01 not zlib") + _chunk(b"IEND", b"")
    response = client.post("/v1/detect", files=parts(frame, image=image))
    assert_error(response, 422, "invalid_input", "image: not a readable PNG image (its image data:")


def test_bytes_that_start_like_a_jpeg_but_are_none_are_415(client: AppClient,  # noqa: F811
                                                            frame: dict[str, bytes]) -> None:  # noqa: F811
    """Every JPEG starts FF D8 FF (the start-of-image marker, then the next marker): FF D8 followed by anything
    else is not a JPEG, so it is the unsupported format (415), not a damaged JPEG (422)."""
    response = client.post("/v1/detect", files=parts(frame, image=b"\xff\xd8\x00" + b"\x00" * 100))
    assert_error(response, 415, "unsupported_media_type", "image: expected a PNG or JPEG image")


def test_every_bad_query_parameter_is_named_in_one_message(client: AppClient,  # noqa: F811
                                                            frame: dict[str, bytes]) -> None:  # noqa: F811
    """Two mistakes, two clauses each starting with its parameter, parted by "; ": a client fixes both at once
    rather than one per round trip."""
    response = client.post("/v1/detect", params={"score_threshold": 2, "emulate_beams": 15}, files=parts(frame))
    message = assert_error(response, 422, "invalid_input")["message"]
    clauses = message.split("; ")
    assert [clause.split(": ")[0] for clause in clauses] == ["score_threshold", "emulate_beams"], message


def test_a_problem_with_no_field_of_its_own_is_said_of_the_request() -> None:
    """A validation error located at the body or query as a whole (no field under it) still starts with what it is
    about, not with an empty name."""
    assert validation_message([{"loc": ("body",), "msg": "Field required"}]) == "request: Field required"


def test_the_schema_bounds_a_detections_score_and_its_corners(client: AppClient) -> None:  # noqa: F811
    """A client generated from /openapi.json gets the answer's shapes: a score in [0, 1], four [x, y] corners."""
    detection = client.get("/openapi.json").json()["components"]["schemas"]["Detection"]["properties"]
    assert (detection["score"]["minimum"], detection["score"]["maximum"]) == (0.0, 1.0)
    corners = detection["bev_corners"]
    assert (corners["minItems"], corners["maxItems"]) == (4, 4)
    assert (corners["items"]["minItems"], corners["items"]["maxItems"]) == (2, 2)


def test_an_unparsable_body_is_said_of_the_request_body(client: AppClient) -> None:  # noqa: F811
    """The framework's own 400 ("Missing boundary...") starts with the part at fault, as every error message."""
    boundary = "0d37f771f3609e9baf6be26654101f5f"
    response = client.post("/v1/detect", content=f"--{boundary}\r\nTrue--{boundary}--\r\n".encode(),
                           headers={"content-type": f"multipart/form-data; boundary={boundary}"})
    message = assert_error(response, 400, "bad_request")["message"]
    assert message.startswith("request body: not parsable as multipart/form-data ("), message


def test_a_long_unknown_path_is_echoed_up_to_200_characters(client: AppClient) -> None:  # noqa: F811
    """The 404 names the path asked for, cut at 200 characters: a client sees its own path, a crafted megabyte of
    path is not echoed back."""
    path = "/v1/" + "p" * 196  # 200 characters
    assert_error(client.get(path), 404, "not_found", f"GET {path}: no such route")
    message = assert_error(client.get(path + "q"), 404, "not_found")["message"]
    assert f"GET {path}: no such route" in message and "q" not in message.split(":")[0], message
