"""Which code made a result: the package's version and, in a git checkout, its commit and whether files differ.

Written into what the tools leave behind (a model directory's manifest, the benchmarks' JSON, a training run's
log), so that two results can be told apart by the code that made them as well as by the machine and package
versions. Standard library only; outside a checkout (an installed wheel, a container) the commit is None.
"""

from __future__ import annotations

import subprocess
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GIT_TIMEOUT_S = 5.0  # a git that hangs (a network file system, a lock) must not stop a benchmark


def _git(*args: str, root: Path) -> str | None:
    """git's output in ``root``, None when git is missing, fails or ``root`` is no checkout."""
    try:
        done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=GIT_TIMEOUT_S,
                              check=False)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def code_version(root: Path = ROOT) -> dict[str, str | bool | None]:
    """``{"lowres3d": version, "commit": sha or None, "dirty": bool or None}`` for the code in ``root``.

    ``dirty``: tracked files differ from the commit (untracked ones, such as data and outputs, do not count)."""
    try:
        version: str | None = metadata.version("lowres3d")
    except metadata.PackageNotFoundError:  # run from a checkout that was never installed
        version = None
    # The checkout's own commit only: a wheel installed inside some other repository must not report that one's.
    toplevel = _git("rev-parse", "--show-toplevel", root=root)
    if toplevel is None or Path(toplevel).resolve() != root.resolve():
        return {"lowres3d": version, "commit": None, "dirty": None}
    commit = _git("rev-parse", "HEAD", root=root)
    status = _git("status", "--porcelain", "--untracked-files=no", root=root)
    return {"lowres3d": version, "commit": commit, "dirty": None if status is None else bool(status)}
