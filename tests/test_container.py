"""The Dockerfile, checked without a container engine: lint, paths, start command, requirements."""

import ast
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCKERFILE = ROOT / "Dockerfile"
REQUIREMENTS = ROOT / "requirements"


def instructions() -> list[tuple[str, str]]:
    """(instruction, arguments) with continuation lines joined and comments dropped."""
    text = re.sub(r"\\\n", " ", DOCKERFILE.read_text())
    rows = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            keyword, _, rest = line.partition(" ")
            rows.append((keyword.upper(), rest.strip()))
    return rows


def test_hadolint_is_clean():
    hadolint = Path(sys.executable).parent / "hadolint"
    result = subprocess.run([str(hadolint), str(DOCKERFILE)], capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stdout + result.stderr


def test_every_copied_path_exists():
    copies = [args for keyword, args in instructions() if keyword == "COPY"]
    assert copies
    for args in copies:
        parts = [p for p in shlex.split(args) if not p.startswith("--")]
        for source in parts[:-1]:
            assert (ROOT / source).exists(), f"COPY source {source} missing"


def test_targets_and_runtime_contents():
    stages = [args for keyword, args in instructions() if keyword == "FROM"]
    assert {"runtime-cpu", "runtime-gpu", "runtime-jetson"} <= {s.split()[-1] for s in stages}
    assert stages[-1].startswith("runtime-${TARGET}")
    copied = " ".join(args for keyword, args in instructions() if keyword == "COPY")
    assert "models/" not in copied.replace("weights/", "") and "export/" not in copied  # torch code stays out
    for name in ("service-cpu.txt", "service-gpu.txt", "service-jetson.txt"):
        lines = [line for line in (REQUIREMENTS / name).read_text().lower().splitlines() if not line.startswith("#")]
        assert not any("torch" in line for line in lines), name
    users = [args for keyword, args in instructions() if keyword == "USER"]
    assert users and users[-1] != "0" and users[-1] != "root"
    health = [args for keyword, args in instructions() if keyword == "HEALTHCHECK"]
    assert health and "/readyz" in health[0]
    env = " ".join(args for keyword, args in instructions() if keyword == "ENV")
    assert "LOWRES3D_TRT_CACHE_DIR=/var/cache/lowres3d/tensorrt" in env
    volumes = [args for keyword, args in instructions() if keyword == "VOLUME"]
    assert volumes and "/var/cache/lowres3d/tensorrt" in volumes[0]


def test_start_command_is_the_documented_one():
    cmd = [args for keyword, args in instructions() if keyword == "CMD"][-1]
    import json

    assert json.loads(cmd) == ["python", "-m", "service"]
    assert "python -m service" in (ROOT / "README.md").read_text()
    deploy = (ROOT / "docs" / "deploy.md").read_text()
    assert "docker run" in deploy and "/readyz" in deploy


def test_every_setting_is_documented_for_the_container():
    from service.settings import Settings

    deploy = (ROOT / "docs" / "deploy.md").read_text()
    for field in Settings.model_fields:
        assert f"LOWRES3D_{field.upper()}" in deploy, field


def test_cpu_requirements_are_the_package_runtime_dependencies():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    declared = {re.split(r"[<>=!]", d)[0].strip() for d in project["dependencies"]}
    listed = {re.split(r"[<>=!]", line)[0].strip() for line in (REQUIREMENTS / "service-cpu.txt").read_text().splitlines()
              if line.strip() and not line.startswith("#")}
    assert listed == declared


def test_runtime_parses_as_python_310():
    """JetPack 6 runs Python 3.10: the image's code must not use newer syntax."""
    for folder in ("pipeline", "service"):
        for path in (ROOT / folder).rglob("*.py"):
            ast.parse(path.read_text(), filename=str(path), feature_version=(3, 10))


@pytest.mark.parametrize("requirements, arch, python", [
    ("service-cpu.txt", "x86_64", "3.11"),
    ("service-cpu.txt", "aarch64", "3.11"),
    ("service-gpu.txt", "x86_64", "3.12"),
])
def test_requirements_resolve(tmp_path, requirements, arch, python):
    platforms = [f"manylinux_2_{v}_{arch}" for v in (28, 27, 17)] + [f"manylinux2014_{arch}"]
    command = [sys.executable, "-m", "pip", "install", "--dry-run", "--quiet", "--ignore-installed",
               "--target", str(tmp_path), "--only-binary=:all:", "--python-version", python,
               "-r", str(REQUIREMENTS / requirements)]
    for platform in platforms:
        command += ["--platform", platform]
    result = subprocess.run(command, capture_output=True, text=True, timeout=300, check=False)
    assert result.returncode == 0, result.stderr[-2000:]
