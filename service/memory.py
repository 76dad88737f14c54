"""glibc's malloc arenas, capped for a service that runs for hours.

glibc gives a thread that finds the arenas it knows busy an arena of its own, up
to 8 per core, and an arena keeps the pages of its largest moment. The service's
threads (event loop, inference workers, ONNX Runtime's) each come to hold the
high-water mark of the uploads and frames they handled, so the resident memory
climbs in steps for a long time. Measured here (2 vCPUs, AMD EPYC Zen 3; edge
models; 4 clients sending the 300 synthetic validation frames in turn, every
10th request broken; two services side by side for 15 min, session 18): the
resident memory ended at 462 MB with glibc's default and 419 MB with two
arenas, climbing 77 and 49 MB after warm-up (trend over the last nine tenths
+135 and +28 MB per hour), at the same throughput (3.99 and 4.06 frames/s).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import sys

log = logging.getLogger(__name__)

_M_ARENA_MAX = -8  # mallopt parameter number, from glibc's malloc.h
SERVICE_ARENAS = 2


def limit_malloc_arenas(count: int = SERVICE_ARENAS) -> bool:
    """Cap glibc's malloc arenas at ``count`` for this process; True if it took effect.

    Call it before the threads start. A no-op returning False where the C library is not glibc, or when
    the operator set ``MALLOC_ARENA_MAX`` (glibc reads it at start; theirs wins).
    """
    if not sys.platform.startswith("linux") or "MALLOC_ARENA_MAX" in os.environ:
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl (Alpine) has no mallopt
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    applied = mallopt(_M_ARENA_MAX, count) == 1
    if applied:
        log.debug("malloc arenas capped at %d", count)
    return applied
