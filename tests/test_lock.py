"""requirements/lock.py and requirements/constraints.txt: the versions the tests run on are the locked ones."""

import importlib.util
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import pytest
from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[1]
LOCK_SCRIPT = ROOT / "requirements" / "lock.py"


def _lock_module():
    """requirements/lock.py, loaded by path (requirements/ is not a package)."""
    spec = importlib.util.spec_from_file_location("lock", LOCK_SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


lock = _lock_module()


def test_this_environment_runs_the_locked_versions():
    """make setup-dev installs with the constraints, so the suite runs on exactly the versions the lock pins (and
    the images ship): a package moved without `make lock`, or a lock edited by hand, fails here by name."""
    done = subprocess.run([sys.executable, str(LOCK_SCRIPT), "--check"], capture_output=True, text=True,
                          timeout=120, check=False)
    assert done.returncode == 0, done.stderr


def test_the_lock_pins_the_services_runtime_at_the_installed_versions():
    pins = lock.read_lock()
    for name in ("fastapi", "starlette", "uvicorn", "h11", "onnxruntime", "numpy", "opencv-python-headless", "torch"):
        assert pins[name] == version(name).split("+")[0], name


def test_closure_follows_requirements_of_requirements_and_their_extras():
    """fastapi needs starlette and pydantic, pydantic needs pydantic-core: all found, at the installed versions;
    an extra's requirements are followed only when the extra is asked for."""
    closure = lock.installed_closure([Requirement("fastapi")])
    for name in ("fastapi", "starlette", "pydantic", "pydantic-core", "anyio"):
        assert closure[name] == version(name), name
    assert "torch" not in closure and "pytest" not in closure
    # onnx's "reference" extra needs Pillow: only with the extra.
    assert "pillow" not in lock.installed_closure([Requirement("onnx")])
    assert lock.installed_closure([Requirement("onnx[reference]")])["pillow"] == version("pillow")


def test_check_names_each_difference(tmp_path):
    pins = {"numpy": "2.0.0", "gone": "1.0", "same": "3.1"}
    found = lock.differences(pins, {"numpy": "2.4.6", "same": "3.1+cpu", "new": "0.5"})
    assert found == ["gone: locked at 1.0, not needed here", "new: installed 0.5, not in the lock",
                     "numpy: installed 2.4.6, locked at 2.0.0"]
    # The command: exit 1 with one line per difference, the lock file left as it was.
    written = tmp_path / "constraints.txt"
    written.write_text("# a comment\nnumpy==1.0.0\n")
    done = subprocess.run([sys.executable, str(LOCK_SCRIPT), "--check", "--out", str(written)],
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 1
    assert f"numpy: installed {version('numpy')}, locked at 1.0.0" in done.stderr.splitlines()
    assert written.read_text() == "# a comment\nnumpy==1.0.0\n"


def test_write_then_check_round_trips(tmp_path):
    out = tmp_path / "constraints.txt"
    done = subprocess.run([sys.executable, str(LOCK_SCRIPT), "--out", str(out)], capture_output=True, text=True,
                          timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert out.read_text() == (ROOT / "requirements" / "constraints.txt").read_text()
    assert lock.read_lock(out)["torch"] == version("torch").split("+")[0]  # the local label dropped


def test_a_malformed_lock_line_is_named(tmp_path):
    bad = tmp_path / "constraints.txt"
    bad.write_text("numpy==2.4.6\nuvicorn>=0.29\n")
    with pytest.raises(ValueError, match=r"constraints.txt, line 2: expected name==version, got 'uvicorn>=0.29'"):
        lock.read_lock(bad)
