"""pipeline.provenance.code_version on real git checkouts made here: the commit, whether tracked files differ,
and None outside a checkout of its own."""

import shutil
import subprocess
from pathlib import Path

import pytest

from pipeline.provenance import code_version

pytestmark = pytest.mark.skipif(shutil.which("git") is None, reason="git is not installed")


def _git(root: Path, *args: str) -> str:
    done = subprocess.run(["git", "-C", str(root), "-c", "user.name=t", "-c", "user.email=t@example.com", *args],
                          capture_output=True, text=True, timeout=30, check=True)
    return done.stdout.strip()


@pytest.fixture
def checkout(tmp_path: Path) -> Path:
    root = tmp_path / "repo"
    root.mkdir()
    _git(root, "init", "-q")
    (root / "a.py").write_text("x = 1\n")
    _git(root, "add", "a.py")
    _git(root, "commit", "-q", "-m", "first")
    return root


def test_a_clean_checkout_gives_its_commit(checkout: Path) -> None:
    code = code_version(checkout)
    assert code["commit"] == _git(checkout, "rev-parse", "HEAD") and code["dirty"] is False


def test_a_changed_tracked_file_is_dirty_and_an_untracked_one_is_not(checkout: Path) -> None:
    (checkout / "outputs.txt").write_text("results\n")  # data and results beside the code: untracked
    assert code_version(checkout)["dirty"] is False
    (checkout / "a.py").write_text("x = 2\n")
    assert code_version(checkout)["dirty"] is True


def test_no_commit_outside_a_checkout_or_inside_another_one(checkout: Path, tmp_path: Path) -> None:
    outside = tmp_path / "plain"
    outside.mkdir()
    assert code_version(outside)["commit"] is None and code_version(outside)["dirty"] is None
    nested = checkout / "site-packages"  # an installed copy inside someone's repository: not that repository's code
    nested.mkdir()
    assert code_version(nested)["commit"] is None


def test_the_package_version_is_the_installed_distributions() -> None:
    from importlib.metadata import version

    assert code_version()["lowres3d"] == version("lowres3d")
