"""Errors a user can act on: each names the file or field and what is wrong with it."""


class InputError(ValueError):
    """A bad input file, array or request field.

    The message always names the source (a file path, an upload field or an
    argument name) and the problem, so that a CLI can print it and a service
    can answer it as a 4xx without a traceback.
    """


# The runtime install (`make demo`, `pip install -e .`) has no torch; the commands that need it say so.
TORCH_MISSING = ("error: training and export need PyTorch, which the runtime install leaves out; "
                 "install it with `make setup-dev` (pip install -e '.[train]', CPU torch 2.13.0 pinned)")
