"""benchmarks/sim_report.py as a command: bad folders and figure paths get one line naming the flag, before any
frame is generated; the generated frames do not outlive the run."""

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "benchmarks" / "sim_report.py"
KITTI = REPO / "tests" / "data" / "kitti" / "training"


def report(*args: str, cwd: Path = REPO, env: dict | None = None, prelude: str = "") -> subprocess.CompletedProcess:
    command = [sys.executable, str(SCRIPT), *args]
    if prelude:  # run the script after some setup in the same interpreter (e.g. hiding a package)
        code = (f"import runpy, sys; {prelude}; sys.argv = {[str(SCRIPT), *args]!r}; "
                f"runpy.run_path({str(SCRIPT)!r}, run_name='__main__')")
        command = [sys.executable, "-c", code]
    return subprocess.run(command, capture_output=True, text=True, timeout=300, check=False, cwd=cwd,
                          env={**os.environ, **(env or {})})


def refused(done: subprocess.CompletedProcess, says: str) -> bool:
    return (done.returncode == 2 and says in done.stderr and "Traceback" not in done.stderr
            and "Warning" not in done.stderr and done.stderr.count("\n") == 1)


def test_a_missing_or_incomplete_kitti_folder_is_named(tmp_path):
    # Was "error: min() arg is an empty sequence" after NumPy's "Mean of empty slice" warnings.
    assert refused(report("--kitti", str(tmp_path / "nope"), "--sim", str(KITTI)), f"--kitti {tmp_path / 'nope'}")
    (tmp_path / "velodyne").mkdir()
    assert refused(report("--kitti", str(tmp_path), "--sim", str(KITTI)), "no image_2/, calib/, label_2/ inside")
    assert refused(report("--sim", str(tmp_path / "nope")), "--sim")


def test_a_figure_that_cannot_be_written_is_refused_before_the_work(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    # Was "error: [Errno 20] Not a directory: …" without the flag, after generating and reading every frame.
    assert refused(report("--sim", str(KITTI), "--figure", str(blocker / "fig.png")), "--figure")
    # A folder, or a name without a picture suffix: matplotlib used to write NAME.png next to it, silently.
    (tmp_path / "pictures").mkdir()
    assert refused(report("--sim", str(KITTI), "--figure", str(tmp_path / "pictures")), "--figure")
    assert not list(tmp_path.glob("*.png"))


def test_the_figure_without_matplotlib_says_what_to_install(tmp_path):
    done = report("--sim", str(KITTI), "--figure", str(tmp_path / "f.png"), prelude="sys.modules['matplotlib'] = None")
    assert refused(done, "make setup-dev")  # was a ModuleNotFoundError traceback after the tables were computed


def test_runs_from_any_folder_and_removes_the_frames_it_generated(tmp_path):
    """The default --kitti is the bundled samples wherever the command runs; generated frames go to a temporary
    folder that is deleted (each default run used to leave 20 frames, ~60 MB, in /tmp)."""
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    done = report("--frames", "1", cwd=tmp_path, env={"TMPDIR": str(scratch)})
    assert done.returncode == 0, done.stderr[-2000:]
    assert "| simulated | 1 |" in done.stdout and "| KITTI | 5 |" in done.stdout
    assert "simulating" in done.stderr  # the progress bar of the generation
    assert list(scratch.iterdir()) == []
