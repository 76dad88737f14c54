"""The service caps glibc's malloc arenas (service/memory.py): counted with glibc's own malloc_stats."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# Eight threads allocating at once (ctypes releases the interpreter lock), then glibc's per-arena report.
CONTENDED = """
import ctypes, sys, threading
sys.path.insert(0, {repo!r})
from service.memory import limit_malloc_arenas
print("applied", limit_malloc_arenas() if sys.argv[1] == "limit" else None, flush=True)
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype = ctypes.c_void_p
start, held = threading.Barrier(8), []
def allocate():
    start.wait()
    held.append([libc.malloc(512) for _ in range(20000)])
threads = [threading.Thread(target=allocate) for _ in range(8)]
for thread in threads:
    thread.start()
for thread in threads:
    thread.join()
libc.malloc_stats()
"""


def _arenas(mode: str, env: dict[str, str] | None = None) -> tuple[str, int]:
    result = subprocess.run([sys.executable, "-c", CONTENDED.format(repo=str(REPO)), mode], capture_output=True,
                            text=True, timeout=120, check=True, env=env)
    return result.stdout.strip(), sum(line.startswith("Arena ") for line in result.stderr.splitlines())


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc only")
def test_threads_share_two_arenas_once_capped():
    applied, capped = _arenas("limit")
    _, uncapped = _arenas("none")
    assert applied == "applied True" and capped <= 2
    assert uncapped > 2  # without the cap the same threads spread over more arenas: the test can fail


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc only")
def test_an_operators_malloc_arena_max_is_left_alone():
    applied, arenas = _arenas("limit", env={**os.environ, "MALLOC_ARENA_MAX": "4"})
    assert applied == "applied False" and 2 < arenas <= 4
