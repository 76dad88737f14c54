"""The sdist and wheel as a user installs them: built offline from a copy of the checkout (sdist first, then the
wheel from the sdist, as `python -m build` does), their files and metadata checked, and the wheel's own files run
from outside any checkout.

Building uses the dev environment's setuptools (``--no-build-isolation``), so no registry is needed. The wheel is
not installed into a fresh venv with its dependencies here: offline there are no wheels of them to install, and a
venv borrowing the dev environment's site-packages would not be an install either. What runs instead is the
wheel's file set (``pip install --target``) on the dev environment's dependencies, with the checkout's editable
finder removed, so a module or data file the wheel lacks fails the run instead of being found in the checkout.
"""

import email.parser
import os
import shutil
import subprocess
import sys
import tarfile
import tomllib
import zipfile
from dataclasses import dataclass
from email.message import Message
from importlib.metadata import version
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.specifiers import SpecifierSet

REPO = Path(__file__).resolve().parents[1]
KITTI = REPO / "tests" / "data" / "kitti" / "training"
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
BUILD_REQUIRES = tomllib.loads((REPO / "pyproject.toml").read_text())["build-system"]["requires"]
PACKAGES = ("pipeline", "models", "export", "service", "simulation", "evaluation")
# Never in a distribution: the test suite and its KITTI samples, data sets, runs, results, the venv, the weights.
KEPT_OUT = ("tests", "data", "weights", "outputs", "runs", ".venv", "benchmarks", "docs", "requirements")
# Not copied into the build's source tree: what the checkout holds beside its sources (never a build input).
NOT_SOURCES = {".git", ".venv", "data", "outputs", "runs", "build", "dist", ".pytest_cache", ".ruff_cache",
               ".hypothesis", "lowres3d.egg-info"}
# The oldest Python the runtime must run on: the Jetson image's (JetPack 6) and ROS 2 Humble's.
OLDEST_PYTHON = "3.10"


@dataclass
class Built:
    sdist: Path
    wheel: Path
    source: Path  # the copy of the checkout both were built from


def _source_copy(dest: Path) -> Path:
    """The checkout's files without its venv, data, results and caches."""
    def ignore(folder: str, names: list[str]) -> set[str]:
        skip = {name for name in names if name == "__pycache__" or name.endswith(".pyc")}
        return skip | (NOT_SOURCES & set(names) if Path(folder) == REPO else set())

    shutil.copytree(REPO, dest, ignore=ignore)
    return dest


def _run(command: list[str], **kwargs) -> subprocess.CompletedProcess:
    """A build step; its own error output when it fails."""
    done = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False, **kwargs)
    assert done.returncode == 0, done.stderr[-3000:]
    return done


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Built:
    # The build backend pyproject.toml names, from the dev environment (the dev extra lists it).
    wanted = Requirement(next(r for r in BUILD_REQUIRES if Requirement(r).name == "setuptools"))
    assert wanted.specifier.contains(version("setuptools")), f"the dev environment needs {wanted} to build"
    root = tmp_path_factory.mktemp("packaging")
    source = _source_copy(root / "src")
    dist = root / "dist"
    _run([sys.executable, "-c", f"import setuptools.build_meta as b; b.build_sdist({str(dist)!r})"], cwd=source)
    (sdist,) = dist.glob("lowres3d-*.tar.gz")
    _run([sys.executable, "-m", "pip", "wheel", str(sdist), "--no-deps", "--no-index", "--no-build-isolation",
          "--quiet", "-w", str(dist)])
    (wheel,) = dist.glob("lowres3d-*.whl")
    return Built(sdist, wheel, source)


def _package_files(source: Path) -> set[str]:
    """Every file of the six packages in the source tree, as a path relative to it."""
    return {path.relative_to(source).as_posix() for package in PACKAGES for path in (source / package).rglob("*")
            if path.is_file() and "__pycache__" not in path.parts}


def _wheel_names(wheel: Path) -> list[str]:
    with zipfile.ZipFile(wheel) as archive:
        return archive.namelist()


def _sdist_names(sdist: Path) -> list[str]:
    """The sdist's files relative to its top folder (lowres3d-VERSION/)."""
    with tarfile.open(sdist) as archive:
        return [name.split("/", 1)[1] for name in archive.getnames() if "/" in name]


def _metadata(wheel: Path) -> Message:
    with zipfile.ZipFile(wheel) as archive:
        (name,) = [n for n in archive.namelist() if n.endswith(".dist-info/METADATA")]
        return email.parser.Parser().parsestr(archive.read(name).decode())


def test_the_wheel_holds_every_file_of_its_packages_and_nothing_else(built):
    """Every module and data file (py.typed, any preset or table a package reads) of the six packages, also in
    subpackages (a folder setuptools' find would miss is missing here), and no test, data set or weight."""
    names = _wheel_names(built.wheel)
    shipped = {name for name in names if ".dist-info/" not in name}
    assert shipped == _package_files(built.source)
    assert "pipeline/py.typed" in shipped  # PEP 561: a user's type checker reads pipeline's annotations
    assert {name.split("/")[0] for name in shipped} == set(PACKAGES)
    assert any(name.endswith(".dist-info/licenses/LICENSE") for name in names)


def test_the_sdist_builds_the_wheel_and_leaves_the_test_suite_in_the_repository(built):
    """The sdist holds what the wheel is built from; not tests/test_*.py (setuptools' default), which cannot run
    without conftest.py, tests/data, weights/ and benchmarks/."""
    names = set(_sdist_names(built.sdist))
    assert _package_files(built.source) <= names
    assert {"pyproject.toml", "README.md", "LICENSE", "PKG-INFO"} <= names
    assert not [name for name in names if name.split("/")[0] in KEPT_OUT]
    assert not [name for name in names if "__pycache__" in name or name.endswith(".pyc")]


def test_the_metadata_declares_what_pyproject_says(built):
    """Requires-Dist (runtime and extras) as in pyproject.toml; the README rendered as Markdown; the licence."""
    metadata = _metadata(built.wheel)
    declared = [Requirement(r) for r in PYPROJECT["dependencies"]]
    for extra, requirements in PYPROJECT["optional-dependencies"].items():
        declared += [Requirement(f'{r}; extra == "{extra}"') for r in requirements]
    assert sorted(map(str, (Requirement(r) for r in metadata.get_all("Requires-Dist")))) == sorted(map(str, declared))
    assert "torch" not in {Requirement(r).name for r in PYPROJECT["dependencies"]}  # the runtime has no torch
    assert sorted(metadata.get_all("Provides-Extra")) == sorted(PYPROJECT["optional-dependencies"])
    assert metadata["Description-Content-Type"] == "text/markdown"
    assert metadata["License-Expression"] == "Apache-2.0"
    assert metadata.get_payload().startswith("# lowres3d")


def test_requires_python_admits_the_jetson_image_python_and_the_code_keeps_to_it(built):
    """The runtime must run on JetPack 6's Python 3.10, so the package must not refuse it; and then nothing the
    wheel holds (the runtime nor models/, export/, simulation/, evaluation/) may use syntax or standard library
    newer than that (vermin knows in which version each came)."""
    requires = SpecifierSet(_metadata(built.wheel)["Requires-Python"])
    assert OLDEST_PYTHON in requires and "3.9" not in requires
    classifiers = _metadata(built.wheel).get_all("Classifier")
    assert f"Programming Language :: Python :: {OLDEST_PYTHON}" in classifiers
    unpacked = built.wheel.parent / "unpacked"
    with zipfile.ZipFile(built.wheel) as archive:
        archive.extractall(unpacked)
    result = subprocess.run(
        [str(Path(sys.executable).with_name("vermin")), f"--target={OLDEST_PYTHON}-", "--violations",
         "--eval-annotations", "--no-tips", "--no-parse-comments", *(str(unpacked / p) for p in PACKAGES)],
        capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-1000:]


# The editable install's finder (appended to sys.meta_path by a .pth file) would find in the checkout any module
# the wheel lacks: it goes first.
_NO_CHECKOUT = """import sys
sys.meta_path[:] = [f for f in sys.meta_path if "__editable__" not in getattr(f, "__module__", "")]
"""
_RUN_MODULE = _NO_CHECKOUT + """import runpy
module, sys.argv = sys.argv[1], sys.argv[1:]
runpy.run_module(module, run_name="__main__", alter_sys=True)
"""
_WHERE = _NO_CHECKOUT + """import importlib, importlib.resources
print(*(importlib.import_module(name).__file__ for name in sys.argv[1:]))
print(importlib.resources.files("pipeline") / "py.typed")
"""


def test_the_wheel_detects_outside_a_checkout(built, tmp_path):
    """The wheel's files alone (no checkout on the path) run `python -m pipeline.detect` on a real frame."""
    site = tmp_path / "site-packages"
    _run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-index", "--quiet", "--target", str(site),
          str(built.wheel)])
    env = {**os.environ, "PYTHONPATH": str(site)}
    run = subprocess.run(
        [sys.executable, "-c", _RUN_MODULE, "pipeline.detect", "--models", str(REPO / "weights" / "edge"),
         "--data", str(KITTI), "--frame", "000006", "--emulate-beams", "16", "--out", str(tmp_path / "out")],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120, check=False)
    assert run.returncode == 0, run.stderr[-2000:]
    assert (tmp_path / "out" / "data" / "000006.txt").read_text().startswith("Car ")
    where = _run([sys.executable, "-c", _WHERE, "pipeline.detect", "service.app", "export.lower", "simulation.run",
                  "evaluation.harness"], cwd=tmp_path, env=env)
    modules, typed = where.stdout.splitlines()
    assert all(Path(path).is_relative_to(site) for path in modules.split()), modules
    assert Path(typed) == site / "pipeline" / "py.typed" and Path(typed).is_file()
