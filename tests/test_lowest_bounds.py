"""requirements/lowest.py: the pins of pyproject.toml's lower bounds that the lowest-versions venv is built with
(docs/deploy.md, "Lowest versions"), and the lines of that recipe held to them. Installs nothing."""

import json
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from packaging.requirements import Requirement

# requirements/ is a namespace package (the lowest-versions run loads this as the plugin -p requirements.lowest)
from requirements import lowest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "requirements" / "lowest.py"
PYPROJECT = ROOT / "pyproject.toml"


def _project(tmp_path: Path, *dependencies: str) -> Path:
    path = tmp_path / "pyproject.toml"
    listed = ", ".join(f"'{d}'" if '"' in d else f'"{d}"' for d in dependencies)
    path.write_text(f'[project]\nname = "x"\ndependencies = [{listed}]\n')
    return path


def test_each_dependency_is_pinned_at_its_lower_bound_with_its_extras_and_marker(tmp_path):
    project = _project(tmp_path, "numpy>=1.26,<3", "tqdm >= 4.66", "x~=1.4", "y[b,a]>=2", "z==0.3",
                       "ort>=1.27; python_version >= '3.11'", "ort>=1.23; python_version < '3.11'")
    assert lowest.lowest_pins(project) == ["numpy==1.26", "tqdm==4.66", "x==1.4", "y[a,b]==2", "z==0.3",
                                           'ort==1.27; python_version >= "3.11"', 'ort==1.23; python_version < "3.11"']
    assert lowest.lowest_pins(project, "3.10")[-1:] == ["ort==1.23"]
    assert lowest.lowest_pins(project, "3.12")[-1:] == ["ort==1.27"]


@pytest.mark.parametrize("python", ["3.10", "3.11", "3.12"])
def test_the_pins_are_the_lowest_versions_pyproject_admits(python):
    """Each dependency this Python takes appears once, at a version its range admits and no lower one would."""
    declared = [Requirement(text) for text in tomllib.loads(PYPROJECT.read_text())["project"]["dependencies"]]
    taken = [r for r in declared if r.marker is None or r.marker.evaluate({"python_version": python})]
    pins = [Requirement(pin) for pin in lowest.lowest_pins(python=python)]
    assert [pin.name for pin in pins] == [r.name for r in taken]
    for pin, requirement in zip(pins, taken, strict=True):
        (spec,) = pin.specifier
        assert spec.operator == "==" and requirement.specifier.contains(spec.version), (pin, requirement)
        assert not requirement.specifier.contains(f"{spec.version}.dev0", prereleases=True), (pin, requirement)


def test_the_command_prints_one_pin_a_line():
    done = subprocess.run([sys.executable, str(SCRIPT), "--python", "3.10"], capture_output=True, text=True,
                          timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == lowest.lowest_pins(python="3.10")


@pytest.mark.parametrize(("text", "says"), [
    ('[project]\ndependencies = ["numpy>=1.26", "fastapi"]\n', "fastapi: expected one lower bound (>=, ~=, ==), found 0"),
    ('[project]\ndependencies = ["numpy>=1.26,>=1.20"]\n', "numpy>=1.20,>=1.26: expected one lower bound"),
    ('[project]\ndependencies = ["numpy>>1"]\n', "'numpy>>1': "),  # packaging's words follow
    ('[project]\nname = "x"\n', "no [project] dependencies"),
    ("dependencies = [", "not TOML"),
])
def test_a_project_file_it_cannot_pin_is_one_line_naming_it(tmp_path, capsys, text, says):
    path = tmp_path / "pyproject.toml"
    path.write_text(text)
    assert lowest.main(["--pyproject", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {path}: ") and says in err and err.count("\n") == 1, err


def test_the_documented_recipe_installs_the_pins():
    """docs/deploy.md's lowest-versions venv is built with exactly the pins for its Python (a bound moved in
    pyproject.toml and not there fails here), and names the pins Python 3.10 takes instead."""
    deploy = (ROOT / "docs" / "deploy.md").read_text()
    block = re.search(r"\*\*Lowest versions\.\*\*.*?```bash\n(.*?)```", deploy, re.DOTALL)
    assert block, "docs/deploy.md: no bash block after **Lowest versions.**"
    lines = block.group(1).replace("\\\n", " ")
    (installed,) = re.findall(r"^/tmp/lowest311/bin/pip install ((?:[\w.\[\],-]+==[\w.]+ *)+)$", lines, re.MULTILINE)
    assert installed.split() == lowest.lowest_pins(python="3.11")
    other = sorted(set(lowest.lowest_pins(python="3.10")) - set(lowest.lowest_pins(python="3.11")))
    assert other and all(f"`{pin}`" in deploy for pin in other), other


def test_what_the_plugin_leaves_out_exists():
    """A renamed test file or test would silently run again in the lowest venv, or a removed one linger here."""
    for names in lowest.LEFT_OUT.values():
        for name in names:
            path, _, test = name.partition("::")
            assert (ROOT / "tests" / path).is_file(), name
            assert not test or f"def {test}(" in (ROOT / "tests" / path).read_text(), name


def test_the_plugin_has_the_models_exported_by_the_interpreter_with_torch(tmp_path, monkeypatch):
    """The export runs in LOWRES3D_EXPORT_PYTHON (here a script that notes its call, then runs this interpreter,
    which has torch) with the keywords given."""
    python = tmp_path / "python"
    python.write_text(f'#!/bin/sh\ntouch "{tmp_path / "called"}"\nexec "{sys.executable}" "$@"\n')
    python.chmod(0o755)
    monkeypatch.setenv("LOWRES3D_EXPORT_PYTHON", str(python))
    lowest.export_elsewhere(lowest.ExportConfig(preset="tiny", out=tmp_path / "models", parity=False,
                                                networks=("pixor",)))
    assert (tmp_path / "called").exists()
    manifest = json.loads((tmp_path / "models" / "manifest.json").read_text())
    assert manifest["preset"] == "tiny" and set(manifest["networks"]) == {"pixor"}
    assert sorted(p.name for p in (tmp_path / "models").iterdir()) == ["manifest.json", "pixor.onnx"]
