"""``python -m service``'s command line where the mutation audit of service/__main__.py found it unpinned: what
--help says of each option, the address checks (a restart on the port of a service that served, an IPv6 wildcard
beside the IPv4 one, a privileged port), the exposure warning as the start writes it, a stop noted between the
models' load and uvicorn's own handlers, and a serving service (its start line, no server header, SIGTERM). The
processes run the shipped models (no torch) with no warm-up, talk over 127.0.0.1 only (elsewhere their sockets
are bound and never listened on, or listened on and never connected to), and are stopped here."""

from __future__ import annotations

import errno
import os
import re
import signal
import socket
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from service.__main__ import (
    AddressError,
    StoppedBeforeServing,
    _address_error,
    _pending_signals,
    bind_listeners,
    build_parser,
    stop_on_signals_until_serving,
)
from tests.test_service_process import START_TIMEOUT_S, _start_fails, _stop, running_service

REPO = Path(__file__).resolve().parents[1]
EDGE = REPO / "weights" / "edge"
QUICK = ("--workers", "1", "--warmup-runs", "0")  # the shipped models, loaded once, not warmed up


def _environ() -> dict[str, str]:
    """This environment without its LOWRES3D_* variables (the test's settings are its command line)."""
    return {k: v for k, v in os.environ.items() if not k.upper().startswith("LOWRES3D_")}


def _help_of(flag: str) -> str:
    """--help's entry for ``flag``, its wrapped lines joined by single spaces."""
    text = " ".join(build_parser().format_help().split())
    start = text.index(f" {flag} ", text.index("options:"))
    end = text.find(" --", start + len(flag) + 2)
    return text[start:end]


@pytest.mark.parametrize(
    ("flag", "says"),
    [("--port", "--port PORT TCP port (0 = any free port) (env LOWRES3D_PORT; default 8000)"),
     ("--provider", "--provider {cpu,cuda,tensorrt}"),
     ("--default-calib", "(env LOWRES3D_DEFAULT_CALIB; default none)"),
     ("--provider", "TensorRT → CUDA → CPU) (env LOWRES3D_PROVIDER)"),
     ("--mirror-tta,", "(env LOWRES3D_MIRROR_TTA; default off)"),
     ("--log-format", "--log-format {text,json}")],
    ids=["number", "choices", "no default", "default in its description", "switch off", "log format"],
)
def test_help_names_each_options_variable_default_and_choices(flag: str, says: str) -> None:
    """Each option's help names its environment variable and its default as the operator reads it (``on``/``off``
    for a switch, ``none`` for unset), and a closed set its choices. An unset option whose description says what
    it then means has that one default only: --provider read "(default: the best available, …) (…; default
    none)"."""
    assert says in _help_of(flag)


def test_a_choice_outside_the_set_is_a_usage_error_naming_the_choices(capsys: pytest.CaptureFixture[str]) -> None:
    """Refused by the command line itself (exit status 2), which lists what it takes."""
    with pytest.raises(SystemExit) as exited:
        build_parser().parse_args(["--provider", "gpu"])
    assert exited.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1] == (
        "python -m service: error: argument --provider: invalid choice: 'gpu' (choose from 'cpu', 'cuda', 'tensorrt')")


def test_a_privileged_port_refused_says_why_and_an_ordinary_one_does_not() -> None:
    """EACCES on a port below 1024 is the privileges; on 1024 and up it is not, and the line does not claim it.
    (The tests run as root, whom the kernel lets bind port 80: the refusal is built as bind would raise it.)"""
    refused = OSError(errno.EACCES, os.strerror(errno.EACCES))
    assert str(_address_error("127.0.0.1", 1023, refused)) == (
        "--port 1023 (LOWRES3D_PORT): permission denied (ports below 1024 need privileges)")
    assert str(_address_error("127.0.0.1", 1024, refused)) == (
        "--host 127.0.0.1 --port 1024: cannot listen there (permission denied)")


def test_a_restart_binds_the_port_its_predecessor_served_on() -> None:
    """A service that served leaves its answered connections in TIME_WAIT on its port for a minute: the next
    start on that port (a restart, a rollout) binds it all the same, as uvicorn would, rather than stop with
    ``address already in use``."""
    (listener,) = bind_listeners("127.0.0.1", 0)
    port = listener.getsockname()[1]
    with listener:
        listener.listen()
        with socket.create_connection(("127.0.0.1", port), timeout=5) as client:
            served, _ = listener.accept()
            served.close()  # the server ends the connection first: its side waits in TIME_WAIT
            client.recv(1)
    try:
        sockets = bind_listeners("127.0.0.1", port)
    except AddressError as exc:
        pytest.fail(f"a restart on the port of a service that served was refused: {exc}")
    for sock in sockets:
        sock.close()


def test_the_ipv6_wildcard_leaves_the_ipv4_one_to_its_own_socket() -> None:
    """IPv6 sockets are IPv6-only (as asyncio binds them): a host that resolves to both wildcards gets a socket
    for each, and the IPv6 one does not take the IPv4 port away. Bound here, never listened on."""
    sockets = bind_listeners("::", 0)
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as ipv4:
            ipv4.bind(("0.0.0.0", sockets[0].getsockname()[1]))
    finally:
        for sock in sockets:
            sock.close()


def test_the_first_of_two_stops_noted_before_the_start_is_the_one_acted_on() -> None:
    """SIGTERM then Ctrl-C during the imports: the SIGTERM (the first) stops the start, as it came first."""
    _pending_signals[:] = [signal.SIGTERM, signal.SIGINT]
    try:
        with pytest.raises(StoppedBeforeServing) as stopped, stop_on_signals_until_serving():
            pass
    finally:
        _pending_signals.clear()
    assert stopped.value.signum == signal.SIGTERM


@pytest.mark.parametrize("token", [False, True], ids=["no token", "a token"])
def test_the_start_warns_of_an_exposed_address_naming_the_port_it_bound(token: bool) -> None:
    """--host 0.0.0.0 --port 0 without a token: the warning names the port the start bound (not 0); with a token,
    none. (No model directory: the start stops after the warning, its sockets bound and never listened on.)"""
    code, output = _start_fails(REPO / "no-such-models", "--host", "0.0.0.0", *(["--token", "t0k"] if token else []))
    assert code == 2, output
    warned = re.search(r"WARNING service: listening on 0\.0\.0\.0 port (\d+) without a token", output)
    if token:
        assert warned is None, output
    else:
        assert warned is not None and int(warned.group(1)) > 0, output
    assert "cannot start: " in output and "model directory not found" in output


def test_a_serving_service_answers_without_naming_its_server_and_sigterm_ends_it_by_the_signal(
    tmp_path: Path,
) -> None:
    """Started without --host, the start's last line names http://127.0.0.1:PORT, where it answers, without a
    ``server`` header (nothing to tell a scanner which server and version it is); a SIGTERM then stops it
    gracefully and the process ends by the signal (status −15), as a supervisor expects of a stopped service."""
    with running_service(EDGE, tmp_path / "service.log", *QUICK, until="/healthz") as running:
        answer = httpx.get(f"{running.url}/healthz", timeout=5)
        running.process.send_signal(signal.SIGTERM)
        code = running.process.wait(20)
        log = running.log()
    assert f"Uvicorn running on {running.url} (Press CTRL+C" in log, log
    assert answer.status_code == 200 and "server" not in answer.headers, answer.headers
    assert code == -signal.SIGTERM, log
    assert "Shutting down" in log and "inference pool stopped" in log
    assert "Traceback" not in log and "without a token" not in log


def test_a_stop_between_the_models_load_and_uvicorns_handlers_is_not_lost(tmp_path: Path) -> None:
    """A SIGTERM in the moment after the models loaded and before uvicorn took the signals over (emulated: sent
    as uvicorn's run begins) is noted, and uvicorn's graceful shutdown follows at its first tick: the service
    does not go on serving until it is killed. (On ::1, never connected to: the line naming where it listened
    shows an IPv6 address in brackets, as a URL needs.)"""
    code = ("import os, signal, sys\nimport uvicorn\nimport service.__main__ as service\n"
            "run = uvicorn.Server.run\n"
            "def late_stop(self, *args, **kwargs):\n"
            "    os.kill(os.getpid(), signal.SIGTERM)\n"
            "    return run(self, *args, **kwargs)\n"
            "uvicorn.Server.run = late_stop\n"
            f"sys.exit(service.main(['--models', {str(EDGE)!r}, '--host', '::1', '--port', '0', *{QUICK!r}]))")
    log_path = tmp_path / "service.log"
    with open(log_path, "w") as log_file:
        process = subprocess.Popen([sys.executable, "-c", code], cwd=REPO, env=_environ(), stdout=log_file,
                                   stderr=subprocess.STDOUT)
    try:
        ended = process.wait(20)
    except subprocess.TimeoutExpired:
        ended = None
    finally:
        _stop(process)
    log = log_path.read_text()
    assert ended == -signal.SIGTERM, f"still serving 20 s after a SIGTERM noted before uvicorn's handlers:\n{log}"
    assert re.search(r"Uvicorn running on http://\[::1\]:[1-9]\d* \(Press CTRL\+C to quit\)", log), log
    assert "Shutting down" in log and "Traceback" not in log


def test_a_stop_inside_onnx_runtimes_session_load_is_not_taken_for_a_bad_model(tmp_path: Path) -> None:
    """A SIGTERM while ONNX Runtime builds a session (emulated: sent as the first one is asked for) stops the
    start as a stop, by the signal: the detector's ``except Exception`` around the session load (a graph ONNX
    Runtime cannot read) must not turn it into ``cannot load it``, exit status 2."""
    code = ("import os, signal, sys\nimport onnxruntime\nimport service.__main__ as service\n"
            "session = onnxruntime.InferenceSession\n"
            "def stopped(*args, **kwargs):\n"
            "    os.kill(os.getpid(), signal.SIGTERM)\n"
            "    return session(*args, **kwargs)\n"
            "onnxruntime.InferenceSession = stopped\n"
            f"sys.exit(service.main(['--models', {str(EDGE)!r}, '--port', '0', *{QUICK!r}]))")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=_environ(), capture_output=True, text=True,
                          timeout=START_TIMEOUT_S, check=False)
    assert done.returncode == -signal.SIGTERM, done.stderr
    assert "SIGTERM before serving: stopped while loading the models; not started" in done.stderr
    assert "cannot load it" not in done.stderr and "Traceback" not in done.stderr
