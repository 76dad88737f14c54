"""The annotations pipeline's py.typed promises a user's type checker: mypy finds nothing in pipeline/ and service/
(pyproject.toml's [tool.mypy]), nor in a user's ``--strict`` code against the public API (tests/data/typing), which
also runs as written; and what mypy found hiding behind an annotation stays fixed."""

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.boxes import BoxRecord
from pipeline.detector import Detector
from pipeline.model_files import ModelFileError
from tests.conftest import KITTI

ROOT = Path(__file__).resolve().parents[1]
EDGE = ROOT / "weights" / "edge"
USER_CODE = ROOT / "tests" / "data" / "typing" / "user_node.py"
# A user's strict check of their own code. The library is read as an installed package is (follow_imports
# silent: its annotations are used, errors inside it are not the user's); its own check is the first test's.
USER_CONFIG = """\
[mypy]
strict = True
python_version = 3.10

[mypy-pipeline.*]
follow_imports = silent
"""
# What the annotations must refuse: a frame loaded without its image has no size (None), and the boxes are an
# array, not a list. Each line number is asserted below, so a library read as untyped (all Any) fails the test.
MISUSE = """\
from pipeline.detector import Detector
from pipeline.frame import load_frame
frame = load_frame("data", "000006", with_image=False)
objects = Detector("models").detect(None, frame.points, frame.calib).to_objects(frame.calib, frame.image_hw)
boxes: list[float] = Detector("models").detect(None, frame.points, None).boxes
"""


def mypy(*args: str, cache: Path) -> subprocess.CompletedProcess[str]:
    """The venv's mypy from the repository's root (so pyproject.toml's [tool.mypy] applies and pipeline is found),
    its cache in a fresh folder: a full check each time, about 10 s."""
    return subprocess.run([sys.executable, "-m", "mypy", "--cache-dir", str(cache), "--no-error-summary", *args],
                          cwd=ROOT, capture_output=True, text=True, timeout=180, check=False)


def test_pipeline_and_service_type_check(tmp_path):
    done = mypy(cache=tmp_path / "cache")
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout == ""


def test_a_users_strict_code_type_checks_against_the_public_api(tmp_path):
    config = tmp_path / "mypy.ini"
    config.write_text(USER_CONFIG)
    misuse = tmp_path / "misuse.py"
    misuse.write_text(MISUSE)
    done = mypy("--config-file", str(config), str(USER_CODE), str(misuse), cache=tmp_path / "cache")
    errors = [line for line in done.stdout.splitlines() if ": error:" in line]
    assert not [line for line in errors if not line.startswith(str(misuse))], done.stdout + done.stderr
    assert [line.split(":")[1] for line in errors] == ["4", "5"], done.stdout + done.stderr
    assert '"to_objects" of "Detections" has incompatible type "tuple[int, int] | None"' in errors[0]


def test_the_users_code_runs_as_it_type_checks(tmp_path):
    """The script passes the library what its annotations allow (a tuple of providers, a generator of result
    objects, float64 read-only rows …): the library takes each."""
    spec = importlib.util.spec_from_file_location("user_node", USER_CODE)
    user_node = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(user_node)
    records = user_node.node(EDGE, KITTI, tmp_path)
    assert records and all(isinstance(record, BoxRecord) for record in records)
    assert (tmp_path / "000006.txt").read_text().count("Car ") >= 1


def _edge_with_training(folder: Path, record: dict) -> Path:
    """weights/edge with ``record`` merged into PIXOR's training record (its ONNX files linked, not copied)."""
    folder.mkdir()
    for onnx in EDGE.glob("*.onnx"):
        (folder / onnx.name).symlink_to(onnx)
    manifest = json.loads((EDGE / "manifest.json").read_text())
    manifest["networks"]["pixor"]["training"].update(record)
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


@pytest.mark.parametrize(("field", "value"), [("input", ["pseudo"]), ("emulate_beams", 16.0),
                                              ("emulate_beams", True)])
def test_a_training_record_of_other_types_is_refused_naming_the_field(tmp_path, field, value):
    """mypy's find behind ``trained_lines(training: dict) -> int | None``: a list as the input failed the Detector
    (and check_models, detect, the service) with a TypeError traceback, and a float line count became
    ``Detector.trained_lines``. A hand-edited manifest gets one line naming the field, as its other tables do."""
    models = _edge_with_training(tmp_path / "models", {field: value})
    with pytest.raises(ModelFileError, match=rf"manifest\.json: networks\.pixor\.training\.{field}: expected"):
        Detector(models)


def test_a_recorded_line_count_is_read_as_an_int(tmp_path):
    with Detector(_edge_with_training(tmp_path / "models", {"input": "lidar16", "emulate_beams": 8})) as detector:
        assert detector.trained_lines == 8 and type(detector.trained_lines) is int
