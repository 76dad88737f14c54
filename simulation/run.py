"""Write N frames in the KITTI layout with a progress bar, optionally in worker processes."""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import signal
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from simulation.frame import FRAME_FILES, SUBDIRS, frame_name, generate_frame, scratch_prefix, write_frame

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunConfig:
    """A generation run: frames ``start … start+frames-1`` of seed ``seed`` into ``out``.

    Frame i is a function of (seed, i) only, so workers and chunking never change
    the bytes. Use disjoint seeds (or disjoint frame ranges of one seed) for train
    and validation. ``split`` names the list file ``<imagesets>/<split>.txt`` of the
    frame ids written; ``imagesets`` defaults to ``out/ImageSets``. Where ``out`` is
    a KITTI root's ``training`` or ``testing`` folder, give the root's ``ImageSets``
    (where OpenPCDet and mmdetection3d read the split lists).
    """

    out: Path
    frames: int
    seed: int
    start: int = 0
    workers: int = 1
    split: str = "train"
    progress: bool = True
    imagesets: Path | None = None

    @property
    def list_file(self) -> Path:
        """The split list this run adds its frame ids to."""
        folder = Path(self.imagesets) if self.imagesets is not None else Path(self.out) / "ImageSets"
        return folder / f"{self.split}.txt"


@dataclass
class RunResult:
    """What a run wrote: frame ids, the list file, and the wall time per frame (seconds)."""

    out: Path
    ids: list[str]
    list_file: Path
    seconds_per_frame: list[float] = field(default_factory=list)


MAX_FRAMES = 1_000_000  # ids 000000 … 999999


def _leave_ctrl_c_to_the_parent() -> None:
    """A worker process ignores Ctrl-C, which reaches every process of the terminal's group, and SIGTERM, which
    a service manager sends to every process of the job: the parent says it once, stops handing out frames, and
    the frames being made finish whole (a worker whose parent is gone ends at its next frame)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)


def _make(seed: int, index: int, out: Path) -> float:
    """Generate and write one frame; returns its wall time (runs in a worker process)."""
    t0 = time.perf_counter()
    write_frame(out, generate_frame(seed, index))
    return time.perf_counter() - t0


def _complete(out: Path, index: int) -> bool:
    """All five files of a frame exist, so an interrupted run can resume: each file is renamed into place
    whole, depth_2 last (write_frame), so a frame killed mid-write is made again."""
    name = frame_name(index)
    return all((out / sub / f"{name}{ext}").exists() for sub, ext in FRAME_FILES)


def _not_written_with_seed(out: Path, seed: int, index: int) -> Path | None:
    """The first file of frame ``index`` in ``out`` that ``seed`` does not make, or None: a run resumed with
    another seed would otherwise mix two data sets, and one given a real KITTI folder would overwrite it.

    Each file present must be the start of what the seed writes (a run killed while writing leaves a file
    cut short), read in the order the frame is written, the calibration and labels first: they are small,
    and exact across library versions, as an image's PNG encoding may not be.
    """
    with tempfile.TemporaryDirectory(prefix="lowres3d-sim-") as scratch:
        for sub in SUBDIRS:
            (Path(scratch) / sub).mkdir(parents=True)
        write_frame(Path(scratch), generate_frame(seed, index))
        name = frame_name(index)
        for sub, ext in (("calib", ".txt"), ("label_2", ".txt"), ("velodyne", ".bin"), ("image_2", ".png")):
            present = out / sub / f"{name}{ext}"
            if present.is_file() and not (Path(scratch) / sub / f"{name}{ext}").read_bytes().startswith(
                    present.read_bytes()):
                return present
    return None


def _check(config: RunConfig) -> None:
    """Refuse bad options with a one-line ValueError, before any folder is made."""
    if config.frames < 1:
        raise ValueError(f"--frames: need at least 1 frame, got {config.frames}")
    if config.workers < 1:
        raise ValueError(f"--workers: need at least 1 worker, got {config.workers}")
    if config.seed < 0:  # numpy's SeedSequence refuses it, after the folders are made
        raise ValueError(f"--seed: must be 0 or more, got {config.seed}")
    if config.start < 0:  # the same for a frame index (the command line refuses it; run() was handed it as is)
        raise ValueError(f"--start: must be 0 or more, got {config.start}")
    if not config.split or Path(config.split).name != config.split or config.split in (".", ".."):
        raise ValueError(f"--split: {config.split!r} names a list file in ImageSets/, not a path")
    if config.start + config.frames > MAX_FRAMES:  # KITTI's ids have six digits, and the lists sort as text
        raise ValueError(f"--start {config.start} --frames {config.frames}: frame ids end at {MAX_FRAMES - 1:06d} "
                         "(KITTI's six digits)")
    out = Path(config.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: exists and is not a directory")
    lists = config.list_file.parent
    if lists.exists() and not lists.is_dir():
        raise ValueError(f"--imagesets {lists}: exists and is not a directory")
    if config.list_file.is_dir():
        raise ValueError(f"--split: {config.list_file} is a directory")


def _remove_scratch(out: Path, indices: list[int]) -> None:
    """Remove the scratch folders that a killed run left for these frames (only these: another run may be
    making other frames of the folder)."""
    prefixes = tuple(scratch_prefix(i) for i in indices)
    for left in out.iterdir():
        if left.name.startswith(prefixes) and left.is_dir():
            shutil.rmtree(left, ignore_errors=True)


def _refuse_another_seeds_folder(out: Path, seed: int, all_indices: list[int], indices: list[int]) -> None:
    """ValueError unless the frames already in ``out`` are this seed's, checked on three: the first frame of
    the run already there whole, the first of those to make that has files already (a KITTI folder has all but
    depth_2), and the folder's first frame outside this run's range (another run's, which --start extends).
    Otherwise the run would mix or overwrite data sets."""
    todo = set(indices)
    whole = next((i for i in all_indices if i not in todo), None)
    begun = next((i for i in indices if any((out / sub / f"{frame_name(i)}{ext}").is_file()
                                           for sub, ext in FRAME_FILES)), None)
    in_range = set(all_indices)
    elsewhere = next((i for i in sorted(int(p.stem) for p in (out / "calib").glob("*.txt") if p.stem.isdigit())
                      if i not in in_range), None)
    for present in (whole, begun, elsewhere):
        foreign = _not_written_with_seed(out, seed, present) if present is not None else None
        if foreign is not None:
            raise ValueError(f"{out}: frame {frame_name(present)} there is not the one seed {seed} makes "
                             f"({foreign} differs); resume with the seed that wrote the folder, or give another --out "
                             "(a folder of real KITTI frames is never written over)")


def run(config: RunConfig) -> RunResult:
    """Generate and write the frames; returns what was written."""
    _check(config)
    out = Path(config.out)
    all_indices = list(range(config.start, config.start + config.frames))
    indices = [i for i in all_indices if not _complete(out, i)]
    _refuse_another_seeds_folder(out, config.seed, all_indices, indices)
    # Made only now: a refused folder (real KITTI frames, another seed's) is left as it was, no empty depth_2/.
    for sub in SUBDIRS:
        (out / sub).mkdir(parents=True, exist_ok=True)
    try:  # now, not after the frames: a list folder that cannot be made would waste the run
        config.list_file.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"--imagesets {config.list_file.parent}: cannot create it ({exc.strerror or exc})") from exc
    _remove_scratch(out, indices)
    if len(indices) < len(all_indices):
        log.info("resuming: %d of %d frames already written", len(all_indices) - len(indices), len(all_indices))
    log.info("writing %d frames (seed %d) to %s with %d worker(s)", len(indices), config.seed, out, config.workers)
    bar = tqdm(total=len(indices), unit="frame", desc="simulating", disable=not config.progress)
    times: list[float] = []
    list_file = config.list_file
    if config.imagesets is None and out.name in ("training", "testing"):
        log.info("the split list goes to %s; OpenPCDet and mmdetection3d read %s (--imagesets)", list_file,
                 out.parent / "ImageSets" / list_file.name)
    try:
        if config.workers == 1:
            for i in indices:
                times.append(_make(config.seed, i, out))
                bar.update()
        else:
            with ProcessPoolExecutor(max_workers=config.workers, initializer=_leave_ctrl_c_to_the_parent) as pool:
                for seconds in pool.map(_make, [config.seed] * len(indices), indices, [out] * len(indices)):
                    times.append(seconds)
                    bar.update()
    except BaseException:  # Ctrl-C, SIGTERM, a full disk: the frames finished are usable as they are, list them
        # The disk that stopped the run may refuse the list too: the first error is the one to tell, and the
        # rerun lists every frame.
        with contextlib.suppress(OSError):
            _extend_list(list_file, [frame_name(i) for i in all_indices if _complete(out, i)])
        raise
    finally:
        bar.close()
    ids = [frame_name(i) for i in all_indices]
    _extend_list(list_file, ids)
    return RunResult(out=out, ids=ids, list_file=list_file, seconds_per_frame=times)


def _extend_list(list_file: Path, ids: list[str]) -> None:
    """Add ``ids`` to a split list: a run that adds frames (--start) never drops the ids an earlier run listed.

    The list is replaced whole (written beside it, then renamed), so a reader never sees it cut short."""
    list_file.parent.mkdir(parents=True, exist_ok=True)
    listed = list_file.read_text(encoding="ascii").split() if list_file.exists() else []
    partial = list_file.with_name(f".{list_file.name}.{os.getpid()}.part")
    try:
        partial.write_text("".join(f"{i}\n" for i in sorted(set(listed) | set(ids))), encoding="ascii")
        os.replace(partial, list_file)
    finally:
        partial.unlink(missing_ok=True)
