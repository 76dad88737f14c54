"""Training runs stopped the ways a shared cluster stops them: SIGKILL while a checkpoint is being written,
SIGTERM (pre-emption), a full disk, a second process given the same run folder, the parent of the
reproduce recipe's job processes killed. Each is a real process, stopped at a chosen moment: a FIFO put where
the run writes a checkpoint holds it mid-write for as long as the test reads nothing from it.

Every run is the tiny depth net on two synthetic frames, one or two epochs.
"""

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import torch

from models.train import main

REPO = Path(__file__).resolve().parents[1]
DEADLINE_S = 60


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> Path:
    """Two synthetic KITTI-layout frames."""
    from simulation.run import RunConfig
    from simulation.run import run as simulate

    out = tmp_path_factory.mktemp("sim")
    for index in range(2):
        simulate(RunConfig(out, frames=1, seed=2, start=index, split="val", progress=False))
    return out


def args(data: Path, out: Path, *extra: str) -> list[str]:
    return ["depth", "--data", str(data), "--preset", "tiny", "--out", str(out), "--epochs", "2", "--batch-size", "1",
            "--max-train-frames", "2", "--max-val-frames", "1", "--compile", "off", "--threads", "1", "--no-progress",
            *extra]


def start(argv: list[str]) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "models.train", *argv], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


class Blocked:
    """A FIFO at ``path``, where a run is to write a checkpoint: the run blocks in that write once the pipe is
    full, until the test drains it (:meth:`drain`)."""

    def __init__(self, path: Path) -> None:
        os.mkfifo(path)
        self.path = path
        self.reader = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # the writer's open() does not wait for one

    def wait_for_writer(self, process: subprocess.Popen) -> None:
        """Return once ``process`` has written into the FIFO and stopped, the pipe full."""
        deadline = time.monotonic() + DEADLINE_S
        while not self._read():
            assert process.poll() is None, process.communicate()[1][-2000:]
            assert time.monotonic() < deadline, "the run never wrote its checkpoint"
            time.sleep(0.05)
        time.sleep(0.5)  # the pipe's 64 KiB fill up; a tiny depth checkpoint is 450 KB

    def drain(self, process: subprocess.Popen) -> None:
        """Read whatever ``process`` writes until it ends."""
        deadline = time.monotonic() + DEADLINE_S
        while process.poll() is None:
            assert time.monotonic() < deadline, "the run did not end"
            self._read()
            time.sleep(0.01)

    def _read(self) -> bool:
        try:
            return bool(os.read(self.reader, 1 << 16))
        except BlockingIOError:  # a writer, nothing written yet
            return False

    def close(self) -> None:
        os.close(self.reader)
        self.path.unlink(missing_ok=True)


@contextmanager
def held_writing_depth_pt(frames: Path, out: Path) -> Iterator[tuple[subprocess.Popen, Blocked]]:
    """A new run in ``out`` stopped in its first checkpoint's write (depth.pt's .tmp a full FIFO); killed and the
    FIFO removed when the block ends."""
    out.mkdir()
    fifo = Blocked(out / "depth.pt.tmp")
    process = start(args(frames, out))
    try:
        fifo.wait_for_writer(process)
        yield process, fifo
    finally:
        process.kill()
        fifo.close()


def weights(run_dir: Path) -> dict[str, torch.Tensor]:
    return torch.load(run_dir / "state.pt", weights_only=False)["networks"]["depth"]


def records(run_dir: Path) -> list[dict]:
    """The run's log, without the seconds each epoch took."""
    lines = (run_dir / "log.jsonl").read_text().splitlines()
    return [{k: v for k, v in json.loads(line).items() if k != "seconds"} for line in lines]


def test_killed_while_writing_its_first_checkpoint_resumes_exactly_and_holds_its_folder(frames, tmp_path, capsys):
    """SIGKILL in the first epoch, mid-way through writing depth.pt: --resume (what a pre-empted job's script
    runs every time) continues the run, to the weights and log of a run never stopped. While the first process
    lives, a second one given the same folder is refused instead of writing its state too."""
    straight = tmp_path / "straight"
    assert main(args(frames, straight)) == 0
    out = tmp_path / "run"
    with held_writing_depth_pt(frames, out) as (process, _):
        assert main(args(frames, out, "--resume")) == 2
        assert capsys.readouterr().err.strip().splitlines()[-1] == (
            f"error: --out: {out} is in use by another training process; wait for it to end (or stop it), then rerun")
        process.kill()
        process.communicate(timeout=DEADLINE_S)
    assert not (out / "depth.pt").exists()  # killed before its first checkpoint was whole
    assert main(args(frames, out, "--resume")) == 0
    assert [r["epoch"] for r in records(out)] == [1, 2] and records(out) == records(straight)
    expected, resumed = weights(straight), weights(out)
    assert all(torch.equal(expected[key], resumed[key]) for key in expected)


def test_sigterm_mid_write_stops_in_one_line_and_the_run_resumes(frames, tmp_path):
    """SIGTERM (pre-emption) while depth.pt is being written: exit status 143, one line saying what the run
    kept and how to go on, no traceback, no half-written file left beside the checkpoints."""
    out = tmp_path / "run"
    with held_writing_depth_pt(frames, out) as (process, fifo):
        process.send_signal(signal.SIGTERM)
        fifo.drain(process)
        _, err = process.communicate(timeout=DEADLINE_S)
    assert process.returncode == 143, err[-2000:]
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1] == (
        f"terminated: {out} has no finished epoch yet; rerun with --resume to start it again")
    assert sorted(p.name for p in out.iterdir()) == ["log.jsonl", "state.pt"]
    done = subprocess.run([sys.executable, "-m", "models.train", *args(frames, out, "--resume")], cwd=REPO,
                          capture_output=True, text=True, timeout=DEADLINE_S, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    assert [r["epoch"] for r in records(out)] == [1, 2]


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full (a device whose writes fail: disk full)")
def test_a_full_disk_is_one_line_and_keeps_the_last_state(frames, tmp_path, capsys):
    """The state's write fails with ENOSPC (it goes to /dev/full): one line naming the file and saying what the
    run keeps, exit status 2; state.pt and the log are those of the epoch before, and no .tmp is left."""
    out = tmp_path / "run"
    assert main(args(frames, out, "--epochs", "1")) == 0
    state, log = (out / "state.pt").read_bytes(), (out / "log.jsonl").read_bytes()
    (out / "state.pt.tmp").symlink_to("/dev/full")
    capsys.readouterr()
    assert main(args(frames, out, "--resume")) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"error: {out / 'state.pt'}: cannot write it (No space left on device); {out} keeps epoch 1 (state.pt); "
        "rerun with --resume to continue from epoch 2")
    assert (out / "state.pt").read_bytes() == state and (out / "log.jsonl").read_bytes() == log
    assert not (out / "state.pt.tmp").exists() and not (out / "state.pt.tmp").is_symlink()


def test_a_file_system_without_folder_locks_still_trains(frames, tmp_path, monkeypatch, caplog):
    """NFS places an exclusive flock only on a file open for writing, which a folder never is (EBADF); Lustre without
    -o flock has none (ENOSYS). Every run there stopped with "cannot write it (Bad file descriptor)": it trains,
    saying it is unguarded; a folder really in use is still refused."""
    import errno
    import fcntl

    real = fcntl.flock

    def unsupported(descriptor: int, operation: int) -> None:
        raise OSError(errno.EBADF, os.strerror(errno.EBADF))

    out = tmp_path / "run"
    monkeypatch.setattr(fcntl, "flock", unsupported)
    assert main(args(frames, out, "--epochs", "1")) == 0
    assert f"{out}: the file system locks no folder (Bad file descriptor)" in caplog.text
    assert [r["epoch"] for r in records(out)] == [1]
    monkeypatch.setattr(fcntl, "flock", real)
    holder = os.open(out, os.O_RDONLY)
    try:
        real(holder, fcntl.LOCK_EX)
        assert main(args(frames, out, "--resume")) == 2
    finally:
        os.close(holder)


def _sleep_and_say(path: str, threads: int | None) -> dict:
    """A job of the test below: writes its pid, then sleeps (spawned: module-level, importable)."""
    Path(path).write_text(str(os.getpid()))
    time.sleep(DEADLINE_S)
    return {}


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
def test_a_job_process_ends_when_the_recipe_is_killed(tmp_path):
    """models.reproduce's parent SIGKILLed (it cannot stop its job processes then): each job ends within seconds,
    instead of training on beside the jobs of the rerun in the same run folders."""
    pid_file = tmp_path / "job.pid"
    script = (
        "import functools, sys\n"
        "from models.schedule import Job, run_jobs\n"
        "from tests.test_train_resume import _sleep_and_say\n"
        "if __name__ == '__main__':\n"
        f"    jobs = [Job('sleeper', functools.partial(_sleep_and_say, {str(pid_file)!r}))]\n"
        "    run_jobs(jobs, lanes=2, progress=False)\n"
    )
    err = tmp_path / "stderr.txt"  # a file, not a pipe: a job left running would hold a pipe open
    with open(err, "w") as stderr:
        parent = subprocess.Popen([sys.executable, "-c", script], cwd=REPO, stderr=stderr)
    try:
        deadline = time.monotonic() + DEADLINE_S
        while not pid_file.is_file() or not pid_file.read_text():
            assert parent.poll() is None, err.read_text()[-2000:]
            assert time.monotonic() < deadline, "the job never started"
            time.sleep(0.1)
        job = int(pid_file.read_text())
        parent.kill()
        parent.wait(timeout=DEADLINE_S)
        deadline = time.monotonic() + 10
        while _alive(job) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not _alive(job), "the job process outlived its parent"
    finally:
        parent.kill()
        if pid_file.is_file() and pid_file.read_text() and _alive(int(pid_file.read_text())):
            os.kill(int(pid_file.read_text()), signal.SIGKILL)
