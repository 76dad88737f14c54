"""Each of the service's upload limits at its edge: a frame exactly at the limit is answered, one unit past it is
refused with a 4xx naming the part (or the body) and the limit.

The limits are documented as inclusive ("at most", "the most"): an integrator sizing a rig's uploads to the limit
must not find it is one less. Through the app over ASGI with the real tiny models and KITTI frame 000006, as
``test_service.py``; the images past a limit are PNG headers alone, refused before any decoding.
"""

from __future__ import annotations

import io
import struct
import zlib
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
from PIL import Image

from service.inputs import MAX_CALIB_BYTES, MAX_JPEG_SCANS, MAX_PNG_CHUNKS
from tests.test_service import AppClient, assert_error, frame, parts, service, tiny_models  # noqa: F401 - fixtures

SERVICE_DOC = Path(__file__).parents[1] / "docs" / "service.md"
KITTI_IMAGE = Path(__file__).parent / "data" / "kitti" / "training" / "image_2" / "000006.png"
WIDTH, HEIGHT = struct.unpack(">II", KITTI_IMAGE.read_bytes()[16:24])  # its IHDR: 1238×374
CROP_W, CROP_H = 1216, 352  # the tiny preset's depth-completion crop (as the shipped models')
POINTS = 1000  # --max-points of the app below
SCORE_ALL = {"score_threshold": 0.0}


def _png_header(width: int, height: int) -> bytes:
    """A PNG signature and IHDR chunk (CRC right), nothing after: refused before decoding whatever it claims."""
    ihdr = b"IHDR" + struct.pack(">II", width, height) + b"\x08\x02\x00\x00\x00"
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + ihdr + struct.pack(">I", zlib.crc32(ihdr))


def _scan(frame: dict[str, bytes], count: int) -> bytes:  # noqa: F811
    """The first ``count`` points of the frame's scan (16 bytes each)."""
    return frame["points"][: 16 * count]


def _parts(frame: dict[str, bytes], **replace: bytes) -> dict[str, tuple[str, bytes, str]]:  # noqa: F811
    """The frame's parts with its first :data:`POINTS` points (under the point limit), ``replace`` swapped in."""
    return parts(frame, **{"points": _scan(frame, POINTS), **replace})


@pytest.fixture(scope="module")
def limited(tiny_models: Path) -> Iterator[AppClient]:  # noqa: F811
    """An app whose point and pixel limits are the test frame's own sizes."""
    with service(tiny_models, max_points=POINTS, max_image_pixels=WIDTH * HEIGHT) as app_client:
        yield app_client


def test_points_at_the_limit_are_answered_and_one_more_is_refused(limited: AppClient, frame: dict[str, bytes]) -> None:  # noqa: F811
    assert limited.post("/v1/detect", files=_parts(frame)).status_code == 200
    response = limited.post("/v1/detect", files=_parts(frame, points=_scan(frame, POINTS + 1)))
    assert_error(response, 422, "invalid_input", f"points: {POINTS + 1} points is more than the limit of {POINTS}")


def test_an_image_of_as_many_pixels_as_the_limit_is_answered(limited: AppClient, frame: dict[str, bytes]) -> None:  # noqa: F811
    """The limit is the frame's own pixel count: it is answered; a header of one pixel more (either side) is refused
    naming the size and the limit, before the missing image data could be noticed."""
    assert limited.post("/v1/detect", files=_parts(frame)).status_code == 200
    for width, height in ((WIDTH + 1, HEIGHT), (WIDTH, HEIGHT + 1)):
        response = limited.post("/v1/detect", files=_parts(frame, image=_png_header(width, height)))
        assert_error(response, 422, "invalid_input", f"image: {width}×{height} pixels is more than the limit of "
                     f"{WIDTH * HEIGHT} pixels")


def test_an_image_of_exactly_the_crop_is_answered_and_one_pixel_less_is_refused(
    limited: AppClient, frame: dict[str, bytes]  # noqa: F811
) -> None:
    image = cv2.imdecode(np.frombuffer(frame["image"], np.uint8), cv2.IMREAD_COLOR)
    # The crop KITTI's depth completion takes: the bottom rows, centred (the calibration still fits it well enough).
    left = (WIDTH - CROP_W) // 2
    exact = cv2.imencode(".png", image[HEIGHT - CROP_H :, left : left + CROP_W])[1].tobytes()
    response = limited.post("/v1/detect", params=SCORE_ALL, files=_parts(frame, image=exact))
    assert response.status_code == 200, response.text
    for width, height in ((CROP_W - 1, CROP_H), (CROP_W, CROP_H - 1)):
        response = limited.post("/v1/detect", files=_parts(frame, image=_png_header(width, height)))
        assert_error(response, 422, "invalid_input", f"image: {width}×{height} pixels is smaller than the model's "
                     f"{CROP_W}×{CROP_H} crop")


@pytest.mark.parametrize(("width", "height"), [(WIDTH, 0), (0, HEIGHT)])
def test_an_image_header_of_no_pixels_is_named_as_such(limited: AppClient, frame: dict[str, bytes],  # noqa: F811
                                                       width: int, height: int) -> None:
    """Not "smaller than the crop": a header of 0 rows or columns is no image a camera takes."""
    response = limited.post("/v1/detect", files=_parts(frame, image=_png_header(width, height)))
    assert_error(response, 422, "invalid_input", f"image: the header says {width}×{height} pixels")


def test_a_calibration_of_the_largest_size_is_read_and_one_byte_more_is_refused(
    limited: AppClient, frame: dict[str, bytes]  # noqa: F811
) -> None:
    """Blank lines are skipped by the parser: the frame's own calibration padded to the limit still reads."""
    padded = frame["calib"] + b"\n" * (MAX_CALIB_BYTES - len(frame["calib"]))
    assert len(padded) == MAX_CALIB_BYTES
    answered = limited.post("/v1/detect", files=_parts(frame, calib=padded))
    assert answered.status_code == 200, answered.text
    response = limited.post("/v1/detect", files=_parts(frame, calib=padded + b"\n"))
    assert_error(response, 422, "invalid_input", f"calib: {MAX_CALIB_BYTES + 1} bytes", f"at most {MAX_CALIB_BYTES}")


def _progressive_jpeg(scans: int) -> bytes:
    """A grey KITTI-sized progressive JPEG of exactly ``scans`` scans: PIL's own, its last scan (a refinement of
    a few bytes) repeated. Each start-of-scan marker is one scan."""
    buffer = io.BytesIO()
    Image.fromarray(np.full((HEIGHT, WIDTH, 3), 128, np.uint8)).save(buffer, "JPEG", progressive=True)
    data = buffer.getvalue()
    end = data.rindex(b"\xff\xd9")
    last = data[data.rindex(b"\xff\xda") : end]
    own = data.count(b"\xff\xda")
    assert own < scans and last.count(b"\xff\xda") == 1
    return data[:end] + last * (scans - own) + data[end:]


def test_a_jpeg_of_as_many_scans_as_the_limit_is_answered(limited: AppClient, frame: dict[str, bytes]) -> None:  # noqa: F811
    at_limit = _progressive_jpeg(MAX_JPEG_SCANS)
    assert at_limit.count(b"\xff\xda") == MAX_JPEG_SCANS
    response = limited.post("/v1/detect", files=_parts(frame, image=at_limit))
    assert response.status_code == 200, response.text
    response = limited.post("/v1/detect", files=_parts(frame, image=_progressive_jpeg(MAX_JPEG_SCANS + 1)))
    assert_error(response, 422, "invalid_input", f"image: a JPEG of {MAX_JPEG_SCANS + 1} scans is more than the "
                 f"limit of {MAX_JPEG_SCANS}")


def _multipart(frame: dict[str, bytes]) -> tuple[bytes, dict[str, str]]:  # noqa: F811
    """A small frame's multipart body (its 1000 first points) and its Content-Type."""
    request = httpx.Request("POST", "http://service/v1/detect", files=_parts(frame))
    return request.read(), {"content-type": request.headers["content-type"]}


def test_a_body_of_exactly_the_limit_is_answered_and_one_byte_more_is_413(
    tiny_models: Path, frame: dict[str, bytes]  # noqa: F811
) -> None:
    """By its Content-Length and, sent chunked without one, by the bytes counted as they arrive. The byte more is
    an epilogue after the close delimiter, which the service otherwise ignores (RFC 2046)."""
    body, headers = _multipart(frame)

    async def chunked(data: bytes) -> AsyncIterator[bytes]:
        for start in range(0, len(data), 65536):
            yield data[start : start + 65536]

    with service(tiny_models, max_body_bytes=len(body)) as app_client:
        for send in (lambda data: data, chunked):
            response = app_client.post("/v1/detect", content=send(body), headers=headers)
            assert response.status_code == 200, response.text
            response = app_client.post("/v1/detect", content=send(body + b"\n"), headers=headers)
            assert_error(response, 413, "body_too_large", f"larger than the limit of {len(body)} bytes")


def test_the_limits_are_the_ones_the_service_doc_gives() -> None:
    """docs/service.md's table of errors tells integrators each fixed limit: the code keeps to it."""
    errors = next(line for line in SERVICE_DOC.read_text().splitlines() if line.startswith("| 422 | `invalid_input`"))
    assert f"a JPEG of more than {MAX_JPEG_SCANS} scans" in errors
    assert f"of more than {MAX_PNG_CHUNKS:,} chunks" in errors
    assert MAX_CALIB_BYTES == 64 * 1024 and "over 64 KiB" in errors
