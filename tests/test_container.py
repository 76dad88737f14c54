"""The Dockerfile, checked without a container engine: lint, paths and build context, start command, health
check, requirements and the GPU target's version pins."""

import ast
import json
import os
import re
import shlex
import socket
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCKERFILE = ROOT / "Dockerfile"
DOCKERIGNORE = ROOT / ".dockerignore"
REQUIREMENTS = ROOT / "requirements"
# Never in the image, never sent to the builder: data sets, training runs, the venv, torch code, tests.
HEAVY_OR_TORCH = ("data", "runs", ".venv", "outputs", "models", "export", "tests", ".git", "benchmarks")


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


def build_args(stage_name: str | None = None) -> dict[str, str]:
    """ARG defaults: the global ones (before the first FROM), and those of one stage when named (a stage's
    ARG shadows a global one; two stages may give the same name different defaults)."""
    rows = [(k, r) for k, r in instructions()]
    first_from = next(i for i, (k, _) in enumerate(rows) if k == "FROM")
    scope = rows[:first_from] + (stage(stage_name) if stage_name else [])
    args = {}
    for keyword, rest in scope:
        if keyword == "ARG" and "=" in rest:
            name, _, value = rest.partition("=")
            args[name] = value.strip('"')
    return args


def stage(name: str) -> list[tuple[str, str]]:
    """The instructions of one build stage (``FROM … AS name`` up to the next FROM)."""
    rows, inside = [], False
    for keyword, rest in instructions():
        if keyword == "FROM":
            inside = rest.split()[-1] == name
        elif inside:
            rows.append((keyword, rest))
    assert rows, f"no stage {name}"
    return rows


# ------------------------------------------------------------------ .dockerignore, with Docker's rules
def _pattern_regex(pattern: str) -> re.Pattern:
    """Docker's (moby/patternmatcher) pattern: filepath.Match syntax plus ``**`` for any number of folders."""
    out, i = "^", 0
    while i < len(pattern):
        char = pattern[i]
        if char == "*":
            if pattern[i:i + 2] == "**":
                i += 1
                if pattern[i + 1:i + 2] == "/":  # "**/" matches zero or more folders
                    i += 1
                    out += "(.*/)?"
                else:
                    out += ".*"
            else:
                out += "[^/]*"
        elif char == "?":
            out += "[^/]"
        elif char == "[":
            end = pattern.index("]", i)
            out += pattern[i:end + 1]
            i = end
        elif char == "\\":
            i += 1
            out += re.escape(pattern[i])
        else:
            out += re.escape(char)
        i += 1
    return re.compile(out + "$")


def dockerignore_rules(text: str) -> list[tuple[bool, re.Pattern, str]]:
    """(is_exception, regex, pattern) per line, as Docker reads them: comments and blanks dropped, paths
    cleaned (a trailing or leading / removed)."""
    rules = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        exception = line.startswith("!")
        pattern = os.path.normpath(line[1:].strip() if exception else line).lstrip("/")
        rules.append((exception, _pattern_regex(pattern), pattern))
    return rules


def ignored(path: str, rules: list[tuple[bool, re.Pattern, str]]) -> bool:
    """Whether Docker leaves ``path`` (relative, with /) out of the build context: the last rule that matches
    the path or one of its parent folders decides."""
    parts = path.split("/")
    candidates = ["/".join(parts[:n]) for n in range(1, len(parts) + 1)]
    verdict = False
    for exception, regex, _ in rules:
        if any(regex.match(candidate) for candidate in candidates):
            verdict = not exception
    return verdict


def build_context(root: Path, rules) -> list[str]:
    """Every file Docker would send to the builder (folders with no exception below them are not walked)."""
    exceptions = [pattern for exception, _, pattern in rules if exception]

    def may_hold_an_exception(folder: str) -> bool:
        return any(p.startswith(folder + "/") or p == folder or not re.match(r"[\w.-]", p[:1] or "*")
                   for p in exceptions)

    files = []
    for current, folders, names in os.walk(root):
        rel = os.path.relpath(current, root).replace(os.sep, "/")
        rel = "" if rel == "." else rel + "/"
        folders[:] = [f for f in folders if not ignored(rel + f, rules) or may_hold_an_exception(rel + f)]
        files += [rel + n for n in names if not ignored(rel + n, rules)]
    return files


def test_the_dockerignore_matcher_follows_docker():
    rules = dockerignore_rules("*\n!weights/edge/\n**/__pycache__\n")
    assert not ignored("weights/edge/depth.onnx", rules)
    assert ignored("weights/edge-int8/depth.onnx", rules)  # "weights/edge" is not a prefix of "weights/edge-int8"
    assert ignored("weights/edge/__pycache__/x.pyc", rules) and ignored("data/sim/x.bin", rules)


def test_build_context_holds_every_copied_file_and_nothing_heavy():
    """A COPY source that .dockerignore leaves out fails the build ("not found") although the path exists here."""
    rules = dockerignore_rules(DOCKERIGNORE.read_text())
    context = build_context(ROOT, rules)
    for args in (args for keyword, args in instructions() if keyword == "COPY"):
        for source in [p for p in shlex.split(args) if not p.startswith("--")][:-1]:
            source = source.rstrip("/")
            on_disk = [str(p.relative_to(ROOT)) for p in (ROOT / source).rglob("*") if p.is_file()
                       and "__pycache__" not in p.parts] if (ROOT / source).is_dir() else [source]
            assert on_disk, source
            missing = [f for f in on_disk if f not in context]
            assert not missing, f"COPY {source}: .dockerignore leaves {missing[:3]} out of the build context"
    heavy = [f for f in context if f.split("/")[0] in HEAVY_OR_TORCH or f.startswith("weights/edge-lidar")]
    assert not heavy, heavy[:5]
    size = sum((ROOT / f).stat().st_size for f in context)
    assert size < 50e6, f"build context of {size / 1e6:.0f} MB"


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
    assert "LICENSE /app/LICENSE" in copied  # Apache-2.0: the licence travels with the code and weights
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
    rows = set(re.findall(r"^\| `LOWRES3D_(\w+)` \|", deploy, re.MULTILINE))
    for field in Settings.model_fields:  # a row of the settings table, not a mention in the prose
        assert field.upper() in rows, field
    # Each default the table gives as a literal is the setting's own (the shutdown grace's once said 60).
    literal = dict(re.findall(r"^\| `LOWRES3D_(\w+)` \| `([^`]+)`", deploy, re.MULTILINE))
    assert len(literal) >= 10
    for name, shown in literal.items():
        default = Settings.model_fields[name.lower()].default
        if default is None:  # derived at start (MODELS/trt_cache): the table says from what
            continue
        default = str(default).lower() if isinstance(default, bool) else default
        if isinstance(default, Path):  # the checkout's weights/edge, absolute
            default = default.relative_to(ROOT).as_posix()
        assert shown == str(default) or (isinstance(default, float) and float(shown) == default), (name, shown)


def test_service_requirements_are_the_package_runtime_dependencies():
    """Each image installs the package's runtime dependencies with its own ONNX Runtime build, but not onnx,
    which only the benchmarks' peak micro-benchmark imports (not pipeline/ or service/: tests/test_detector.py)."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    runtime = {re.split(r"[<>=!]", d)[0].strip() for d in project["dependencies"]} - {"onnx"}
    expected = {
        "service-cpu.txt": runtime,
        "service-gpu.txt": runtime - {"onnxruntime"} | {"onnxruntime-gpu"},
        "service-jetson.txt": runtime - {"onnxruntime"},  # onnxruntime-gpu from the Jetson index (Dockerfile)
    }
    for name, packages in expected.items():
        listed = {re.split(r"[<>=!#\s]", line)[0] for line in (REQUIREMENTS / name).read_text().splitlines()
                  if line.strip() and not line.startswith("#")}
        assert listed == packages, name


def test_the_declared_licence_ships_as_its_text():
    """pyproject declares Apache-2.0; the package and the image carry the licence's text, and KITTI's samples keep theirs."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["license"] == "Apache-2.0" and project["license-files"] == ["LICENSE"]
    text = (ROOT / "LICENSE").read_text()
    assert "Apache License" in text and "Version 2.0, January 2004" in text and "END OF TERMS AND CONDITIONS" in text
    assert "Attribution-NonCommercial-ShareAlike 3.0" in (ROOT / "tests" / "data" / "README.md").read_text()


def test_runtime_parses_as_python_310():
    """JetPack 6 runs Python 3.10: the image's code must not use newer syntax."""
    for folder in ("pipeline", "service"):
        for path in (ROOT / folder).rglob("*.py"):
            ast.parse(path.read_text(), filename=str(path), feature_version=(3, 10))


def test_runtime_uses_nothing_of_the_standard_library_newer_than_python_310():
    """Syntax is not all: ``typing.Self`` or ``enum.StrEnum`` parse on 3.10 and fail there at import, so the
    Jetson image's service would not start. vermin knows in which version each standard-library name came."""
    result = subprocess.run(
        [str(Path(sys.executable).with_name("vermin")), "--target=3.10-", "--violations", "--eval-annotations", "--no-tips",
         "--no-parse-comments", str(ROOT / "pipeline"), str(ROOT / "service")],
        capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-1000:]


@pytest.mark.parametrize("requirements, arch, python", [
    ("service-cpu.txt", "x86_64", "3.11"),
    ("service-cpu.txt", "aarch64", "3.11"),
    ("service-gpu.txt", "x86_64", "3.12"),  # Ubuntu 24.04's Python
])
def test_requirements_resolve(tmp_path, requirements, arch, python):
    """Each image's pip install, as its stage runs it: the CPU and GPU images with the locked versions (and
    the GPU image with its pinned onnxruntime-gpu), the Jetson image without (its Python 3.10)."""
    platforms = [f"manylinux_2_{v}_{arch}" for v in (28, 27, 17)] + [f"manylinux2014_{arch}"]
    command = [sys.executable, "-m", "pip", "install", "--dry-run", "--quiet", "--ignore-installed",
               "--target", str(tmp_path), "--only-binary=:all:", "--python-version", python,
               "-r", str(REQUIREMENTS / requirements)]
    if requirements != "service-jetson.txt":
        command += ["-c", str(REQUIREMENTS / "constraints.txt")]
    if requirements == "service-gpu.txt":
        command.append(f"onnxruntime-gpu=={build_args('runtime-gpu')['ORT_GPU_VERSION']}")
    for platform in platforms:
        command += ["--platform", platform]
    result = subprocess.run(command, capture_output=True, text=True, timeout=300, check=False)
    assert result.returncode == 0, result.stderr[-2000:]


def test_cpu_and_gpu_images_install_the_locked_versions():
    """The CPU and GPU stages copy requirements/constraints.txt and give it to pip (-c), so an image built
    later installs the versions the tests ran on (tests/test_lock.py); the Jetson stage cannot (Python 3.10)."""
    for name in ("runtime-cpu", "runtime-gpu"):
        rows = stage(name)
        assert ("COPY", "requirements/constraints.txt /tmp/constraints.txt") in rows, name
        installs = [rest for keyword, rest in rows if keyword == "RUN" and "pip install" in rest]
        assert len(installs) == 1 and "-c /tmp/constraints.txt" in installs[0], name
    assert not any("constraints" in rest for _, rest in stage("runtime-jetson"))


def test_jetson_requirements_resolve_for_python_310(tmp_path):
    """JetPack 6's Python 3.10 on arm64 (onnxruntime-gpu itself comes from the Jetson index, not PyPI)."""
    test_requirements_resolve(tmp_path, "service-jetson.txt", "aarch64", "3.10")


# ------------------------------------------------------------------ GPU target: CUDA 12 throughout
def test_gpu_target_pins_onnxruntime_and_tensorrt_to_the_base_images_cuda():
    """Unpinned, apt takes TensorRT's "+cuda13.x" packages and pip a CUDA 13 onnxruntime-gpu (>= 1.27): on the
    CUDA 12 base neither loads and the "GPU" image runs on the CPU."""
    args = build_args("runtime-gpu")
    cuda_major = re.search(r"nvidia/cuda:(\d+)\.", args["GPU_BASE"]).group(1)
    assert re.fullmatch(rf"10\.[\d.]+-1\+cuda{cuda_major}\.\d+", args.get("TENSORRT_VERSION", "")), \
        f"TENSORRT_VERSION must be a TensorRT 10 build for CUDA {cuda_major}: {args.get('TENSORRT_VERSION')}"
    assert re.fullmatch(r"\d+\.\d+\.\d+", args.get("ORT_GPU_VERSION", ""))
    gpu = " ".join(rest for keyword, rest in stage("runtime-gpu") if keyword == "RUN")
    for package in ("libnvinfer10", "libnvinfer-plugin10", "libnvonnxparsers10"):
        assert f"{package}=${{TENSORRT_VERSION}}" in gpu, f"{package} not pinned"
    assert "onnxruntime-gpu==${ORT_GPU_VERSION}" in gpu


def test_pinned_onnxruntime_gpu_is_a_cuda_12_build(tmp_path):
    """The wheel's own [cuda,cudnn] extras name the CUDA it was built for (…-cu12 packages, or CUDA 13 ones).
    Read from the wheel's metadata alone (--no-deps): resolving the NVIDIA packages too took a minute."""
    version = build_args("runtime-gpu")["ORT_GPU_VERSION"]
    report = tmp_path / "report.json"
    tags = [f"manylinux_2_{v}_x86_64" for v in (28, 27, 17)] + ["manylinux2014_x86_64"]
    platforms = [arg for tag in tags for arg in ("--platform", tag)]
    command = [sys.executable, "-m", "pip", "install", "--dry-run", "--quiet", "--ignore-installed", "--no-deps",
               "--target", str(tmp_path / "t"), "--only-binary=:all:", "--python-version", "3.12", *platforms,
               "--report", str(report), f"onnxruntime-gpu=={version}"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=300, check=False)
    assert result.returncode == 0, result.stderr[-2000:]
    requires = json.loads(report.read_text())["install"][0]["metadata"].get("requires_dist", [])
    extras = [r.split(";")[0].strip() for r in requires if re.search(r'extra == "(cuda|cudnn)"', r)]
    nvidia = [re.split(r"[~<>=!]", r)[0].lower() for r in extras if r.lower().startswith("nvidia-")]
    assert nvidia and all(n.endswith("-cu12") for n in nvidia), f"onnxruntime-gpu {version} pulls {nvidia}"


def test_container_user_may_use_a_jetsons_gpu():
    """On a Jetson the GPU device nodes belong to the video group: a user outside it sees no CUDA device."""
    useradd = " ".join(rest for keyword, rest in instructions() if keyword == "RUN" and "useradd" in rest)
    assert re.search(r"(--groups|-G) video\b", useradd), useradd
    assert "--uid 10001" in useradd and [r for k, r in instructions() if k == "USER"][-1] == "10001"


# ------------------------------------------------------------------ the image's environment, run for real
def image_env() -> dict[str, str]:
    """The ENV of the final stage, with the image's /app paths mapped onto this checkout."""
    env = {}
    for keyword, rest in stage("service"):
        if keyword == "ENV":
            for item in shlex.split(rest):
                name, _, value = item.partition("=")
                env[name] = value
    return env


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def test_image_environment_listens_beyond_loopback_and_the_healthcheck_follows_it(tmp_path):
    """The image's ENV makes the service bind every interface (LOWRES3D_HOST), as a published port needs, and
    the HEALTHCHECK command fails before the service started by the image's CMD is ready and passes after.
    The live part binds loopback only: tests talk to 127.0.0.1 and open nothing beyond it."""
    env = image_env()
    assert env.get("LOWRES3D_HOST") == "0.0.0.0"  # 127.0.0.1 in a container is unreachable through -p
    image_settings = {k: v for k, v in env.items() if k.startswith("LOWRES3D_")}
    port = _free_port()
    run_env = {**os.environ, **image_settings, "LOWRES3D_HOST": "127.0.0.1",
               "LOWRES3D_PORT": str(port), "LOWRES3D_MODELS": str(ROOT / "weights" / "edge"),
               "LOWRES3D_TRT_CACHE_DIR": str(tmp_path / "trt"), "LOWRES3D_PROVIDER": "cpu",
               "LOWRES3D_WORKERS": "1", "PYTHONPATH": str(ROOT)}
    health = json.loads(re.sub(r"^(--\S+\s+)*CMD\s+", "", [r for k, r in instructions() if k == "HEALTHCHECK"][-1]))
    health = [sys.executable if health[0] == "python" else health[0], *health[1:]]
    cmd = json.loads([r for k, r in instructions() if k == "CMD"][-1])
    assert subprocess.run(health, env=run_env, capture_output=True, timeout=30, check=False).returncode != 0
    log = (tmp_path / "service.log").open("w")
    process = subprocess.Popen([sys.executable, *cmd[1:]], env=run_env, cwd=tmp_path, stdout=log,
                               stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while subprocess.run(health, env=run_env, capture_output=True, timeout=30, check=False).returncode != 0:
            assert process.poll() is None, (tmp_path / "service.log").read_text()[-2000:]
            assert time.monotonic() < deadline, "HEALTHCHECK never passed"
            time.sleep(0.5)
    finally:
        process.terminate()
        process.wait(timeout=60)
        log.close()
