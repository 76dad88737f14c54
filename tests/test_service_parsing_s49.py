"""How the service reads what a client sends, found by a penetration test (session 49): the multipart boundary
as the parser reads it, an oversized text field, and the calibration's numbers. Through the app over ASGI with the
real tiny models and KITTI frame 000006, as ``test_service.py``; each test failed on the code before its fix."""

from __future__ import annotations

import inspect
import re

import httpx
import pytest
from python_multipart.multipart import parse_options_header
from starlette.formparsers import MultiPartParser

from pipeline.errors import InputError
from pipeline.kitti import parse_calib
from tests.test_service import KITTI, AppClient, assert_error, client, frame, parts, tiny_models  # noqa: F401 - fixtures

SCORE_ALL = {"score_threshold": 0.0}


def _small_frame(frame: dict[str, bytes]) -> dict[str, tuple[str, bytes, str]]:  # noqa: F811
    """The frame's parts with its first 2000 points (a small upload: the boundary is what is under test)."""
    return parts(frame, points=frame["points"][: 16 * 2000])


def _with_boundary(frame: dict[str, bytes], content_type: str, boundary: str) -> tuple[bytes, dict[str, str]]:  # noqa: F811
    """The small frame's multipart body delimited by ``boundary``, sent with this Content-Type."""
    request = httpx.Request("POST", "http://service/v1/detect", files=_small_frame(frame))
    sent = re.search(r"boundary=(\S+)", request.headers["content-type"])
    assert sent is not None
    body = request.read().replace(sent.group(1).encode(), boundary.encode())
    return body, {"content-type": content_type}


# --------------------------------------------------------------------------- 1. the boundary parameter
@pytest.mark.parametrize(
    ("content_type", "boundary"),
    [("multipart/form-data; boundary=XyZbound ; charset=utf-8", "XyZbound"),  # whitespace before ";" is legal
     ("multipart/form-data; xboundary=zzz; boundary=XyZbound", "XyZbound"),  # another parameter ends in "boundary"
     ('multipart/form-data; boundary="Xy Z:=bound" ; charset=utf-8', "Xy Z:=bound"),  # quoted (space, "=", ":")
     ("multipart/form-data;BOUNDARY=XyZbound", "XyZbound")],  # parameter names are case-insensitive
    ids=["space before ;", "xboundary first", "quoted", "no space, upper-case name"],
)
def test_a_whole_body_is_answered_whatever_legal_spelling_its_boundary_parameter_has(
    client: AppClient, frame: dict[str, bytes], content_type: str, boundary: str  # noqa: F811
) -> None:
    """The close delimiter is looked for with the boundary the multipart parser reads: a body it parses whole was
    refused as "a cut-off upload" when the service read another boundary out of the same header."""
    plain = client.post("/v1/detect", params=SCORE_ALL, files=_small_frame(frame))
    assert plain.status_code == 200, plain.text
    body, headers = _with_boundary(frame, content_type, boundary)
    response = client.post("/v1/detect", params=SCORE_ALL, content=body, headers=headers)
    assert response.status_code == 200, response.text
    assert response.json()["detections"] == plain.json()["detections"]
    cut = client.post("/v1/detect", params=SCORE_ALL, content=body[:-100], headers=headers)
    assert_error(cut, 400, "bad_request", "ended before its closing boundary")


# --------------------------------------------------------------------------- 2. a large part sent as a text field
def _body_of(fields: list[tuple[str, str, bytes]], boundary: str = "s49bound") -> tuple[bytes, dict[str, str]]:
    """A multipart body of (name, the Content-Disposition's parameters after ``name``, data) parts."""
    body = b"".join(
        f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"{extra}\r\n\r\n'.encode() + data + b"\r\n"
        for name, extra, data in fields)
    return body + f"--{boundary}--\r\n".encode(), {"content-type": f"multipart/form-data; boundary={boundary}"}


@pytest.mark.parametrize("extra", ["", "; filename*=UTF-8''scan.bin"], ids=["no filename", "filename* only"])
def test_a_real_size_scan_sent_as_a_text_field_is_told_to_be_sent_as_a_file(
    client: AppClient, frame: dict[str, bytes], extra: str  # noqa: F811
) -> None:
    """A text field over Starlette's 1 MiB limit for one (the whole 64-line scan, 1.9 MB) was a 400 "not parsable
    as multipart/form-data (Part exceeded maximum size of 1024KB.)", naming neither the part nor the fix; a small
    one is the 422 "points: sent as a text field". The parser does not say which part it was: the answer says what
    was too large and how each of the service's parts is sent. The installed libraries decide what the part is:
    python-multipart 0.0.20 (the lowest pyproject.toml admits) reads ``filename*=`` as a filename (a file: the
    frame is answered), and Starlette 0.38 (FastAPI 0.112.2's) has no limit for a field (the 422 naming it)."""
    assert len(frame["points"]) > 1024 * 1024
    disposition = f'form-data; name="points"{extra}'
    sent_as_file = b"filename" in parse_options_header(disposition)[1]
    field_limit = "max_part_size" in inspect.signature(MultiPartParser.__init__).parameters
    body, headers = _body_of([("image", '; filename="i.png"', frame["image"]), ("points", extra, frame["points"]),
                              ("calib", '; filename="c.txt"', frame["calib"])])
    response = client.post("/v1/detect", content=body, headers=headers)
    if sent_as_file:
        assert response.status_code == 200, response.text
    elif field_limit:
        error = assert_error(response, 400, "bad_request",
                             "a part sent as a form field (without filename=) is larger than 1024 KB",
                             "send the parts image, points, calib as files", "curl -F points=@FILE")
        assert "not parsable" not in error["message"]
    else:
        assert_error(response, 422, "invalid_input", "points: sent as a text field")
    small, headers = _body_of([("image", '; filename="i.png"', frame["image"]),
                               ("points", extra, frame["points"][: 16 * 2000]),
                               ("calib", '; filename="c.txt"', frame["calib"])])
    response = client.post("/v1/detect", content=small, headers=headers)
    if sent_as_file:
        assert response.status_code == 200, response.text
    else:
        assert_error(response, 422, "invalid_input", "points: sent as a text field")


# --------------------------------------------------------------------------- 3. the calibration's numbers
CALIB_LINES = (KITTI / "calib" / "000006.txt").read_text().splitlines()  # P2 on line 3


def _with_p2(*first: str) -> str:
    """Frame 000006's calibration text with P2's first numbers replaced by ``first``."""
    numbers = CALIB_LINES[2].split(":")[1].split()
    numbers[: len(first)] = first
    return "\n".join(["P2: " + " ".join(numbers) if line.startswith("P2:") else line for line in CALIB_LINES])


@pytest.mark.parametrize("written", ["\u0667\u0662\u0661", "\uff17\uff12\uff11", "7_2_1", "721\u00b2", "0x2d1", "७२१.5"],
                         ids=["arabic-indic", "fullwidth", "underscores", "superscript", "hex", "devanagari"])
def test_a_calibration_number_is_ascii_decimal_or_refused_naming_file_line_and_key(written: str) -> None:
    """Python's float() reads 721 out of "٧٢١", "７２１" and "7_2_1"; no KITTI reader does, and the frame was
    answered 200 with that focal length. Such a number is refused with the file, line and key."""
    with pytest.raises(InputError, match=r"^calib\.txt, line 3: P2 has a non-numeric value \("):
        parse_calib(_with_p2(written), "calib.txt")


@pytest.mark.parametrize(("written", "value"), [("7.183351000000e+02", 718.3351), ("7.183351E+02", 718.3351),
                                               ("+718.3351", 718.3351), ("718.", 718.0), ("718", 718.0),
                                               (".7183351e3", 718.3351), ("7183351e-4", 718.3351)])
def test_every_ascii_decimal_spelling_of_a_number_is_read(written: str, value: float) -> None:
    """What KITTI's files and other tools write (exponents of either case, a sign, no digits on one side of the
    point) is read as before."""
    assert parse_calib(_with_p2(written), "calib.txt").P2[0, 0] == pytest.approx(value, rel=1e-12)


@pytest.mark.parametrize("value", ["nan", "-inf", "Infinity"])
def test_nan_and_infinity_are_still_named_as_non_finite(value: str) -> None:
    with pytest.raises(InputError, match=r"^calib\.txt, line 3: P2 has a non-finite value$"):
        parse_calib(_with_p2(value), "calib.txt")


P2_NUMBERS = CALIB_LINES[2].split(":")[1].split()


@pytest.mark.parametrize(("first", "axis"), [(("-7.183351e+02",), "fx"), ((*P2_NUMBERS[:5], "-7.183351e+02"), "fy"),
                                             (tuple(f"{-float(v):.12e}" for v in P2_NUMBERS), "fx")],
                         ids=["fx negative", "fy negative", "P2 negated"])
def test_a_focal_length_that_is_not_positive_is_refused_naming_p2(first: tuple[str, ...], axis: str) -> None:
    """A rectified camera's P2 = K [I | t] has fx = P2[0,0] > 0 and fy = P2[1,1] > 0; a negative one (a mirrored
    camera, or P2 negated: the same projective map, which the pipeline reads as points behind the camera) was
    answered 200 with boxes. Zero with off-diagonal terms beside it is not singular, and no camera either."""
    with pytest.raises(InputError, match=rf"^calib\.txt: P2's focal length {axis} = P2\[.* is not positive"):
        parse_calib(_with_p2(*first), "calib.txt")
    with pytest.raises(InputError, match=r"^calib\.txt: P2's focal length fx = P2\[0,0\] = 0 is not positive"):
        parse_calib(_with_p2("0", "5e+02", *P2_NUMBERS[2:4], "5e+02"), "calib.txt")


@pytest.mark.parametrize("calib", [_with_p2("\u0667\u0661\u0668.3351"), _with_p2("-7.183351e+02")],
                         ids=["arabic-indic digits", "negative fx"])
def test_the_service_answers_such_a_calibration_422_naming_it(
    client: AppClient, frame: dict[str, bytes], calib: str  # noqa: F811
) -> None:
    response = client.post("/v1/detect", files=parts(frame, calib=calib.encode(), points=frame["points"][: 16 * 2000]))
    assert_error(response, 422, "invalid_input", "calib", "P2")
