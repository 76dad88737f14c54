"""Errors a user can act on: each names the file or field and what is wrong with it."""

from collections.abc import Iterator
from contextlib import contextmanager


class InputError(ValueError):
    """A bad input file, array or request field.

    The message always names the source (a file path, an upload field or an
    argument name) and the problem, so that a CLI can print it and a service
    can answer it as a 4xx without a traceback.
    """


@contextmanager
def in_frame(where: str) -> Iterator[None]:
    """Prefix an InputError raised inside with ``where`` (a folder and frame): the Detector and emulate_beams
    name only the field ("points: …"), which in a run over thousands of frames says nothing of which one."""
    try:
        yield
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from exc


# The runtime install (`make demo`, `pip install -e .`) has no torch; the commands that need it say so.
TORCH_MISSING = ("error: this command needs PyTorch, which the runtime install leaves out; install it with "
                 "`make setup-dev` in a checkout (pip install -e '.[train]'), or the wheel's 'train' extra "
                 "(pip install 'lowres3d-….whl[train]'): torch 2.13.0, pinned in version only; for the CPU build, "
                 "install it first from PyTorch's CPU index, as the README says")
