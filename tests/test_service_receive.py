"""``--receive-timeout-s`` bounds the upload, not the answer: a body trickled in past the deadline is 408, however
often its bytes come; a frame whose body arrived in time is answered however long it then waits for a worker.

The app in-process over ASGI, as ``test_service.py`` does (httpx hands the app the body chunk by chunk, as the
client yields it), with the real tiny models and KITTI frame 000006.
"""

from __future__ import annotations

import threading
import time
from collections.abc import AsyncIterator
from pathlib import Path

import anyio
import httpx

from tests.test_service import assert_error, frame, parts, service, tiny_models  # noqa: F401 - fixtures


def _multipart(frame: dict[str, bytes]) -> tuple[bytes, dict[str, str]]:  # noqa: F811
    """The frame's multipart body (its first 2000 points: a small upload) and its Content-Type."""
    request = httpx.Request("POST", "http://service/v1/detect", files=parts(frame, points=frame["points"][: 16 * 2000]))
    return request.read(), {"content-type": request.headers["content-type"]}


def test_a_body_trickled_in_past_the_deadline_is_408(tiny_models: Path, frame: dict[str, bytes]) -> None:  # noqa: F811
    """Each piece comes well within the deadline, the whole body does not: the deadline runs from the request's
    start (a client sending a byte now and then must not hold a place in the pool for ever). The refusal comes at
    the deadline, while the client is still sending: a check made only once the body is in would read every piece
    and answer only after the whole trickle (3 s here, six times the deadline)."""
    body, headers = _multipart(frame)
    pieces = 15
    handed = 0  # pieces the client has sent: the app reads the body only as it asks for it

    async def trickle() -> AsyncIterator[bytes]:
        nonlocal handed
        step = len(body) // pieces + 1
        for start in range(0, len(body), step):
            await anyio.sleep(0.2)
            handed += 1
            yield body[start : start + step]

    with service(tiny_models, receive_timeout_s=0.5) as app_client:
        started = time.monotonic()
        response = app_client.post("/v1/detect", content=trickle(), headers=headers)
        elapsed = time.monotonic() - started
        assert_error(response, 408, "request_timeout", "request body: not received within 0.5 s")
        assert response.headers["connection"] == "close"
        # At 0.5 s two or three pieces are in; a slow machine may let a few more through, never most of them.
        assert handed < pieces // 2, handed
        assert elapsed < 0.5 + 1.0, elapsed  # refused at the deadline, not after the whole body (3 s)
        assert app_client.post("/v1/detect", content=body, headers=headers).status_code == 200


def test_a_frame_waiting_for_a_worker_past_the_receive_timeout_is_answered(
    tiny_models: Path, frame: dict[str, bytes]  # noqa: F811
) -> None:
    """Its body came at once; the frame then waits behind a busy worker three times the receive timeout. The
    answer is its detections, not a 408: once the body is in, only the request timeout bounds the wait."""
    body, headers = _multipart(frame)
    with service(tiny_models, workers=1, queue_size=1, receive_timeout_s=0.2) as app_client:
        pool = app_client.app.state.runtime.pool
        release = threading.Event()
        held = app_client.portal.start_task_soon(pool.run, lambda _d, _c: release.wait(30), 60)
        timer = threading.Timer(0.6, release.set)
        try:
            deadline = time.monotonic() + 10
            while pool.depth != (0, 1):  # the worker is busy
                assert time.monotonic() < deadline
                time.sleep(0.01)
            timer.start()
            response = app_client.post("/v1/detect", content=body, headers=headers)
            assert response.status_code == 200, response.text
            assert response.json()["timings_ms"]["queue_wait"] > 300  # it did wait past the receive timeout
        finally:
            timer.cancel()
            release.set()
            held.result(30)
