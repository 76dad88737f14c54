"""What one upload can make the service's image decoders do: bounded by what the frame is, not by how it is encoded.

The pixel limit bounds an image's memory, but libjpeg's time grows with a JPEG's scans and libpng's with a PNG's
compressed data, and libpng writes a line to stderr (the service's log) for every ancillary chunk it finds fault
with. Each test sends a crafted image that a real camera never writes, through the app over ASGI as
``test_service.py`` does, with the real tiny models; and the start-up's warning for an address open to other
machines without a token.
"""

from __future__ import annotations

import io
import struct
import zlib
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from pipeline.errors import InputError
from pipeline.kitti import decode_image
from service.__main__ import exposure_warning
from service.inputs import MAX_JPEG_SCANS, png_for_decoding
from tests.test_service import AppClient, assert_error, frame, parts, service, tiny_models  # noqa: F401 - fixtures

KITTI_IMAGES = Path(__file__).parent / "data" / "kitti" / "training" / "image_2"
WIDTH, HEIGHT = 1242, 375  # KITTI's camera: at least the models' crop


@pytest.fixture(scope="module")
def client(tiny_models: Path) -> Iterator[AppClient]:  # noqa: F811
    with service(tiny_models) as app_client:
        yield app_client


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _png(raw: bytes, before_idat: bytes = b"", interlace: int = 0, width: int = WIDTH, height: int = HEIGHT) -> bytes:
    """An 8-bit RGB PNG whose image data is ``raw`` (filter bytes included), ``before_idat`` chunks after IHDR."""
    header = _chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, interlace))
    return (b"\x89PNG\r\n\x1a\n" + header + before_idat + _chunk(b"IDAT", zlib.compress(raw, 9))
            + _chunk(b"IEND", b""))


GREY_ROWS = (b"\x00" + b"\x80" * 3 * WIDTH) * HEIGHT


def _scans(data: bytes) -> list[bytes]:
    """A JPEG's scans, each its SOS segment and entropy-coded data (up to the next marker that is not a restart)."""
    scans, start = [], data.find(b"\xff\xda")
    while start != -1:
        end = start + 2 + int.from_bytes(data[start + 2 : start + 4], "big")
        while not (data[end] == 0xFF and data[end + 1] != 0x00 and not 0xD0 <= data[end + 1] <= 0xD7):
            end += 1
        scans.append(data[start:end])
        start = data.find(b"\xff\xda", end)
    return scans


def _progressive_jpeg(extra_scans: int) -> bytes:
    """A grey KITTI-sized progressive JPEG (libjpeg's 10 scans), its smallest AC scan repeated ``extra_scans``
    times more: a few bytes each (one end-of-band run), each a pass over every block of the image."""
    buffer = io.BytesIO()
    Image.fromarray(np.full((HEIGHT, WIDTH, 3), 128, np.uint8)).save(buffer, "JPEG", progressive=True)
    data = buffer.getvalue()
    scans = _scans(data)
    smallest = min(scans[1:], key=len)
    end = data.rindex(b"\xff\xd9")
    return data[:end] + smallest * extra_scans + data[end:]


# --------------------------------------------------------------------------- JPEG: scans
def test_a_jpeg_of_thousands_of_scans_is_refused_before_the_queue(client: AppClient, frame: dict[str, bytes]) -> None:  # noqa: F811
    """A crafted progressive JPEG costs libjpeg a pass over the image per scan, 12 bytes each: 100,000 of them (1.2 MB)
    held a worker 4.6 s in decoding, which no deadline stops (and 32 MB, two minutes). Counted from the bytes."""
    bomb = _progressive_jpeg(2_000)
    assert cv2.imdecode(np.frombuffer(bomb, np.uint8), cv2.IMREAD_COLOR).shape == (HEIGHT, WIDTH, 3)  # decodable
    response = client.post("/v1/detect", files=parts(frame, image=bomb))
    scans = bomb.count(b"\xff\xda")
    assert_error(response, 422, "invalid_input", "image", f"{scans} scans", str(MAX_JPEG_SCANS))


def test_an_ordinary_progressive_jpeg_is_decoded(client: AppClient, frame: dict[str, bytes]) -> None:  # noqa: F811
    """libjpeg's progressive script has 10 scans, a baseline JPEG 1: both far under the limit."""
    rgb = cv2.cvtColor(decode_image(frame["image"]), cv2.COLOR_RGB2BGR)
    progressive = cv2.imencode(".jpg", rgb, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1].tobytes()
    assert client.post("/v1/detect", files=parts(frame, image=progressive)).status_code == 200


# --------------------------------------------------------------------------- PNG: image data past its size
def test_a_png_whose_image_data_inflates_past_its_size_is_refused(client: AppClient, frame: dict[str, bytes]) -> None:  # noqa: F811
    """libpng inflates every byte of IDAT data, past the last row too: a megabyte of zlib is a gigabyte of zeros,
    2 s of a worker (and 32 MB over a minute) for an image the header says is KITTI's size."""
    bomb = _png(GREY_ROWS + bytes(200_000_000))  # ~200 kB on the wire
    assert len(bomb) < 500_000
    response = client.post("/v1/detect", files=parts(frame, image=bomb))
    assert_error(response, 422, "invalid_input", "image", "inflates to more than its header's size")


def test_png_image_data_is_counted_exactly_also_interlaced() -> None:
    """One byte of image data past the header's size is refused; an Adam7 image (7 passes, each row its filter
    byte) of odd sizes decodes to the same pixels as it did without the check."""
    rng = np.random.default_rng(0)
    passes = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))
    for height, width in ((HEIGHT, WIDTH), (9, 17), (1, 1)):
        pixels = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
        raw = b"".join(b"\x00" + row.tobytes() for x0, y0, dx, dy in passes for row in pixels[y0::dy, x0::dx]
                       if row.size)
        interlaced = _png(raw, interlace=1, width=width, height=height)
        assert np.array_equal(decode_image(png_for_decoding(interlaced)), pixels)
        with pytest.raises(InputError, match="inflates to more than its header's size"):
            png_for_decoding(_png(raw + b"\x00", interlace=1, width=width, height=height))


@pytest.mark.parametrize("bits", [1, 2, 4])
def test_a_png_of_fewer_bits_a_pixel_is_counted_by_its_packed_rows(bits: int) -> None:
    """A palette PNG of 1, 2 or 4 bits a pixel packs several pixels a byte; a width that is no multiple of them
    leaves each row's last byte partly filled, which the image data holds all the same: such an image decodes as
    it does without the check (a row counted one byte short would refuse it as a decompression bomb)."""
    rng = np.random.default_rng(bits)
    colours = 2**bits
    image = Image.fromarray(rng.integers(0, colours, (7, 13), dtype=np.uint8), "L").convert("P")
    image.putpalette([value for i in range(colours) for value in (i * 16, 255 - i * 16, i * 8)])
    buffer = io.BytesIO()
    image.save(buffer, "PNG", bits=bits)
    data = buffer.getvalue()
    assert (data[24], data[25]) == (bits, 3)  # IHDR: the bit depth asked for, colour type 3 (palette)
    assert np.array_equal(decode_image(png_for_decoding(data)), decode_image(data))


def test_the_bundled_pngs_decode_to_the_same_pixels(tmp_path: Path) -> None:
    """What the check keeps of a camera's PNG decodes exactly as the whole file did; ancillary chunks (text, gamma,
    physical size) are dropped without a change to OpenCV's pixels."""
    for path in sorted(KITTI_IMAGES.glob("*.png")):
        data = path.read_bytes()
        assert np.array_equal(decode_image(png_for_decoding(data)), decode_image(data)), path.name
    noted = _png(GREY_ROWS, _chunk(b"gAMA", struct.pack(">I", 45455)) + _chunk(b"tEXt", b"Software\x00camera")
                 + _chunk(b"pHYs", struct.pack(">IIB", 3780, 3780, 1)))
    assert _chunk_kinds(png_for_decoding(noted)) == [b"IHDR", b"IDAT", b"IEND"]
    assert np.array_equal(decode_image(png_for_decoding(noted)), decode_image(noted))


def _chunk_kinds(png: bytes) -> list[bytes]:
    """The chunk types of a PNG, in order."""
    kinds, pos = [], 8
    while pos < len(png):
        kinds.append(png[pos + 4 : pos + 8])
        pos += 12 + int.from_bytes(png[pos : pos + 4], "big")
    return kinds


def test_the_image_data_reaches_the_decoder_inflated_once() -> None:
    """The check inflates the image data to count it; the decoder gets it in stored blocks (a copy to inflate),
    so a camera's PNG is not inflated twice: one IDAT, as large as the rows it holds, the same pixels."""
    data = (KITTI_IMAGES / "000006.png").read_bytes()
    kept = png_for_decoding(data)
    assert _chunk_kinds(kept) == [b"IHDR", b"IDAT", b"IEND"]
    width, height = struct.unpack(">II", data[16:24])
    rows = height * (1 + width * 3)  # each row a filter byte and its RGB pixels
    assert len(data) < rows < len(kept) < rows + 1_000  # stored: the rows plus a few bytes a 64 kB block
    assert np.array_equal(decode_image(kept), decode_image(data))


# --------------------------------------------------------------------------- PNG: chunks libpng writes about
def test_bad_ancillary_png_chunks_reach_neither_libpng_nor_the_log(
    client: AppClient, frame: dict[str, bytes], capfd: pytest.CaptureFixture[str]  # noqa: F811
) -> None:
    """libpng writes "libpng warning: abCd: CRC error" to stderr, the service's log, for each ancillary chunk with a
    wrong CRC (and so for duplicate or misplaced ones): 10,000 of them, 120 kB, were 10,000 log lines, past the
    filters that keep the noise clients cause out of the log. They are dropped before decoding; the frame is
    detected as it is without them."""
    broken = struct.pack(">I", 0) + b"abCd" + b"\x00\x00\x00\x00"  # an empty chunk of an unknown kind, its CRC wrong
    image = frame["image"][:33] + broken * 2_000 + frame["image"][33:]  # after the signature and IHDR
    capfd.readouterr()
    noisy = client.post("/v1/detect", files=parts(frame, image=image), params={"score_threshold": 0})
    plain = client.post("/v1/detect", files=parts(frame), params={"score_threshold": 0})
    assert noisy.status_code == plain.status_code == 200, noisy.text
    assert noisy.json()["detections"] == plain.json()["detections"]
    assert "libpng" not in capfd.readouterr().err


def test_transparency_is_kept_once_and_its_duplicates_dropped(capfd: pytest.CaptureFixture[str]) -> None:
    """tRNS changes a palette image's decoding, so the first is kept; libpng warns of each duplicate ("tRNS:
    duplicate"), so those are dropped like the ancillary chunks no pixel depends on."""
    buffer = io.BytesIO()
    palette = Image.fromarray(np.random.default_rng(1).integers(0, 256, (40, 50, 3), dtype=np.uint8)).convert("P")
    palette.save(buffer, "PNG", transparency=3)
    once = buffer.getvalue()
    start = once.index(b"tRNS") - 4
    end = start + 12 + int.from_bytes(once[start : start + 4], "big")
    repeated = once[:end] + once[start:end] * 300 + once[end:]
    capfd.readouterr()
    decode_image(repeated)
    assert capfd.readouterr().err.count("libpng warning") >= 300  # what the decoder alone writes
    kept = png_for_decoding(repeated)
    assert kept.count(b"tRNS") == 1
    assert np.array_equal(decode_image(kept), decode_image(once))
    assert "libpng" not in capfd.readouterr().err


@pytest.mark.parametrize("chunk", [b"zTXt", b"iCCP"])
def test_compressed_ancillary_png_chunks_are_not_inflated(chunk: bytes) -> None:
    """zTXt, iTXt and iCCP are inflated by libpng (up to its 8 MB a chunk): fifty of them in 5 MB took 0.9 s.
    They are gone before libpng sees the file."""
    bomb = _chunk(chunk, b"k\x00\x00" + zlib.compress(bytes(50_000_000), 9))
    kept = png_for_decoding(_png(GREY_ROWS, bomb * 3))
    assert _chunk_kinds(kept) == [b"IHDR", b"IDAT", b"IEND"] and b"k\x00\x00" not in kept
    assert np.array_equal(decode_image(kept), decode_image(_png(GREY_ROWS)))


def test_an_unknown_critical_png_chunk_is_named() -> None:
    """A critical chunk (upper-case first letter) a decoder does not know means it cannot decode the file."""
    with pytest.raises(InputError, match=r"unknown critical chunk 'ABCD'"):
        png_for_decoding(_png(GREY_ROWS, _chunk(b"ABCD", b"")))


def test_a_png_chunk_longer_than_the_file_is_named() -> None:
    """A chunk whose length field runs past the file's end (a damaged length, the file ending with IEND all the
    same) is named with the length it claims, not taken for a file that ends early."""
    data = (KITTI_IMAGES / "000006.png").read_bytes()
    length_at = data.index(b"IDAT") - 4
    damaged = data[:length_at] + struct.pack(">I", 10_000_000) + data[length_at + 4 :]
    with pytest.raises(InputError, match=r"a chunk of 10000000 bytes runs past its end"):
        png_for_decoding(damaged)


# --------------------------------------------------------------------------- start-up: an open address
def test_listening_beyond_loopback_without_a_token_is_warned_of() -> None:
    """The container listens on 0.0.0.0 with no token by default: every client on the vehicle's network could run
    frames and read /v1/model. The start says so (from the bound addresses, so a host name counts as what it is)."""
    warning = exposure_warning(["0.0.0.0"], 8000, token_set=False)
    assert warning is not None and "0.0.0.0 port 8000 without a token" in warning and "LOWRES3D_TOKEN" in warning
    assert exposure_warning(["::", "0.0.0.0"], 8000, token_set=True) is None
    assert exposure_warning(["127.0.0.1", "::1"], 8000, token_set=False) is None
    assert "192.168.1.20" in (exposure_warning(["192.168.1.20", "fe80::1%eth0"], 1, token_set=False) or "")
