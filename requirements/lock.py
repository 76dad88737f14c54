"""The exact versions the tests run on, as pip constraints: requirements/constraints.txt.

    python requirements/lock.py            # write it from this environment (make lock)
    python requirements/lock.py --check    # exit 1, naming each package installed at another version

The file pins every package the project installs (its runtime, `train` and `dev` extras, and what
they pull in), each at the version installed here. `make setup` / `make setup-dev` install with it
(`pip install -c`), so CI tests those versions; the CPU and GPU images install their runtime with it,
so an image built later ships what was tested, not whatever the registry holds that day (the service
subclasses uvicorn's HTTP protocol: service/protocol.py). To move a dependency: install the new version
in the dev environment, `make lock`, `make test`, and commit the file with the change (docs/deploy.md).
"""

from __future__ import annotations

import argparse
import sys
import tomllib
from importlib.metadata import PackageNotFoundError, distribution
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script: the repository's packages

from pipeline.cli import HelpFormatter, examples, quiet_interrupt, unwritable

ROOT = Path(__file__).resolve().parents[1]
CONSTRAINTS = ROOT / "requirements" / "constraints.txt"
EXTRAS = ("train", "dev")  # what `make setup-dev` installs
HEADER = """\
# The versions the tests ran on: pip constraints for `make setup`, `make setup-dev` and the CPU and GPU
# images (the Jetson image's Python 3.10 cannot take all of them: docs/deploy.md). Written by
# `python requirements/lock.py` (make lock) from the dev environment; do not edit by hand.
"""


def project_requirements(root: Path = ROOT, extras: tuple[str, ...] = EXTRAS) -> list[Requirement]:
    """pyproject.toml's dependencies and those of ``extras``."""
    project = tomllib.loads((root / "pyproject.toml").read_text())["project"]
    listed = list(project["dependencies"])
    for extra in extras:
        listed += project["optional-dependencies"][extra]
    return [Requirement(text) for text in listed]


def installed_closure(roots: list[Requirement]) -> dict[str, str]:
    """Every distribution the ``roots`` need here, with what they need in turn: canonical name → installed
    version. Markers are evaluated for this interpreter and platform, with each requirement's extras.
    Raises PackageNotFoundError naming a package that should be installed and is not."""
    versions: dict[str, str] = {}
    pending = [(root, frozenset(root.extras)) for root in roots]
    followed: set[tuple[str, frozenset[str]]] = set()
    while pending:
        requirement, extras = pending.pop()
        name = canonicalize_name(requirement.name)
        if (name, extras) in followed:
            continue
        followed.add((name, extras))
        found = distribution(requirement.name)
        versions[name] = found.version
        for text in found.requires or []:
            needed = Requirement(text)
            if needed.marker is None or any(needed.marker.evaluate({"extra": extra}) for extra in ("", *extras)):
                pending.append((needed, frozenset(needed.extras)))
    return versions


def lock_lines(versions: dict[str, str]) -> list[str]:
    """``name==version`` lines, sorted; a local label (torch's ``+cpu``) dropped, so the pin also matches the
    build a registry serves under the plain version."""
    return [f"{name}=={version.split('+')[0]}" for name, version in sorted(versions.items())]


def read_lock(path: Path = CONSTRAINTS) -> dict[str, str]:
    """The constraints file as canonical name → version."""
    pins: dict[str, str] = {}
    for number, line in enumerate(path.read_text().splitlines(), 1):
        line = line.split("#")[0].strip()
        if not line:
            continue
        name, separator, version = line.partition("==")
        if not separator or not version:
            raise ValueError(f"{path}, line {number}: expected name==version, got {line!r}")
        pins[canonicalize_name(name)] = version
    return pins


def differences(pins: dict[str, str], versions: dict[str, str]) -> list[str]:
    """What differs between the lock and this environment, one line each (empty: they agree)."""
    found = []
    for name in sorted(pins.keys() | versions.keys()):
        installed = versions.get(name, "").split("+")[0]
        if name not in versions:
            found.append(f"{name}: locked at {pins[name]}, not needed here")
        elif name not in pins:
            found.append(f"{name}: installed {installed}, not in the lock")
        elif installed != pins[name]:
            found.append(f"{name}: installed {installed}, locked at {pins[name]}")
    return found


@quiet_interrupt("--out is as it was (written only at the end)")
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
                                     prog="python requirements/lock.py", description=__doc__.split("\n\n")[0],
                                     epilog=examples("python requirements/lock.py --check"),
                                     formatter_class=HelpFormatter)
    parser.add_argument("--check", action="store_true",
                        help="only compare: exit 1 naming each package installed at another version than the lock")
    parser.add_argument("--out", type=Path, default=CONSTRAINTS, metavar="FILE",
                        help=f"the constraints file (default {CONSTRAINTS.relative_to(ROOT)})")
    args = parser.parse_args(argv)
    try:
        versions = installed_closure(project_requirements())
    except PackageNotFoundError as missing:  # the environment, not the lock: a usage error (2), not a difference
        print(f"error: {missing.name} is not installed: run make setup-dev first", file=sys.stderr)
        return 2
    if args.check:
        try:
            found = differences(read_lock(args.out), versions)
        except OSError as exc:
            print(f"error: --out {args.out}: {exc.strerror or exc}", file=sys.stderr)
            return 2
        except ValueError as unreadable:  # names the file and the line
            print(f"error: {unreadable}", file=sys.stderr)
            return 2
        for line in found:
            print(line, file=sys.stderr)
        return 1 if found else 0
    try:
        args.out.write_text(HEADER + "\n".join(lock_lines(versions)) + "\n")
    except OSError as exc:
        print(unwritable(args.out, exc), file=sys.stderr)
        return 2
    print(f"wrote {args.out}: {len(versions)} packages")
    return 0


if __name__ == "__main__":
    sys.exit(main())
