"""`pvm-label match`: dense disparity on a CPU with no network: the labeler's census SGM of the left view with its
row fill (:mod:`pvm_labeler.dense`: ``sgm_left`` + ``fill_rows_nearest``, the evaluation's dense-SGM baseline), for
one pair of image files or every pair of a dataset, written with the project's writers.

Formats (``--format``, several allowed): ``png`` KITTI 16-bit PNG (round(d x 256), 0 = no disparity, so a valid
disparity of exactly 0 and the holes of ``--no-fill`` both read back as unknown), ``pfm`` and ``npy`` (float32, NaN
= no disparity). Files are ``OUT/<name>.<ext>``: the left image's stem for a pair, the reader's frame id for a dataset.

Search range: ``max_disp`` when given, else (datasets) the pair's own hint (Middlebury / ETH3D ``calib.txt`` ndisp)
or the dataset's default, else ``LabelerConfig().max_disp`` (192). Datasets run ``jobs`` pairs at once over
:func:`pvm_labeler.parallel.run_tasks` (joblib loky), each with ``cores // jobs`` numba threads. A dataset pair that
cannot be read (a corrupt or truncated image, left/right sizes that differ) is skipped, the others are written, and
``OUT/failures.json`` ({"frame_id", "error"} records) lists the skipped ones, as ``optstereo-predict --dataset`` does.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from pvm_labeler.common import io
from pvm_labeler.common.atomic import record_failures
from pvm_labeler.common.datasets import DEFAULT_MAX_DISP, PairRef, check_pair_sizes, discover, load_pair
from pvm_labeler.common.errors import InputError, PVMError
from pvm_labeler.config import LabelerConfig
from pvm_labeler.dense import fill_rows_nearest, sgm_left
from pvm_labeler.job import progress
from pvm_labeler.parallel import numba_threads_per_worker, run_tasks, thread_budget

logger = logging.getLogger(__name__)

#: Disparity files `pvm-label match` writes (``io.write_kitti_disp``, ``io.write_pfm``, ``io.write_npy``).
MATCH_FORMATS: tuple[str, ...] = ("png", "pfm", "npy")


def match_arrays(left: np.ndarray, right: np.ndarray, max_disp: int | None = None, fill: bool = True,
                 cfg: LabelerConfig | None = None) -> npt.NDArray[np.float32]:
    """Dense SGM disparity of one pair: ``sgm_left``, then (``fill``) ``fill_rows_nearest``.

    left, right: (H, W, 3) uint8 RGB (or (H, W) grey). Returns (H, W) float32, left(x) matches right(x - d); NaN
    where SGM gives none (with ``fill``: only in rows that have no value at all).
    """
    disp, _ = sgm_left(left, right, cfg or LabelerConfig(), max_disp)
    return fill_rows_nearest(disp) if fill else disp


def write_disparity(out_dir: Path, name: str, disp: np.ndarray, formats: tuple[str, ...]) -> dict[str, Path]:
    """Write ``disp`` as ``out_dir/<name>.<ext>`` per format (atomically); returns format -> path."""
    unknown = sorted(set(formats) - set(MATCH_FORMATS))
    if unknown:
        raise InputError(f"unknown output formats {unknown}; choose from {', '.join(MATCH_FORMATS)}")
    out_dir.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    for fmt in formats:
        paths[fmt] = out_dir / f"{name}.{fmt}"
        io.write_disparity_file(paths[fmt], disp)
    return paths


def _match_named(left: np.ndarray, right: np.ndarray, max_disp: int | None, fill: bool, what: str
                 ) -> npt.NDArray[np.float32]:
    """:func:`match_arrays` with the SGM's input errors (search range wider than the image, ...) naming ``what``."""
    try:
        return match_arrays(left, right, max_disp, fill)
    except InputError as exc:
        raise InputError(f"{what}: {exc}") from exc


def match_pair(left_path: Path, right_path: Path, out_dir: Path, *, formats: tuple[str, ...] = ("png",),
               max_disp: int | None = None, fill: bool = True) -> dict[str, Path]:
    """Match two image files and write ``out_dir/<left stem>.<ext>``; returns format -> path.

    Raises:
        InputError: a file is missing or unreadable, or the two sizes differ (naming both files).
    """
    left, right = io.read_image(left_path), io.read_image(right_path)
    if left.shape != right.shape:
        raise InputError(f"left/right sizes differ: {left.shape[:2]} vs {right.shape[:2]} (H, W): {left_path}, "
                         f"{right_path}")
    disp = _match_named(left, right, max_disp, fill, f"{left_path}, {right_path}")
    return write_disparity(Path(out_dir), Path(left_path).stem, disp, formats)


@dataclass
class MatchTask:
    """One dataset pair for a worker (picklable)."""

    ref: PairRef
    out_dir: Path
    formats: tuple[str, ...]
    max_disp: int | None
    fill: bool
    threads: int
    paths: dict[str, Path] = field(default_factory=dict)
    error: str | None = None  # why the pair could not be read (then nothing was written for it)


def _match_task(task: MatchTask) -> MatchTask:
    """Match and write one pair; a pair that cannot be read comes back with ``error`` set and no ``paths``."""
    with thread_budget(task.threads):
        try:
            sample = load_pair(task.ref)
        except PVMError as exc:
            task.error = str(exc)
            return task
        max_disp = task.max_disp or sample.max_disp or DEFAULT_MAX_DISP.get(task.ref.meta.get("dataset", ""))
        disp = _match_named(sample.left, sample.right, max_disp, task.fill,
                            f"pair {task.ref.frame_id} ({task.ref.left}, {task.ref.right})")
    task.paths = write_disparity(task.out_dir, task.ref.frame_id, disp, task.formats)
    return task


def match_dataset(dataset: str, root: Path | None, out_dir: Path, *, split: str = "training",
                  formats: tuple[str, ...] = ("png",), max_disp: int | None = None, fill: bool = True, jobs: int = 1,
                  limit: int | None = None, quiet: bool = False, reader_options: dict[str, Any] | None = None,
                  ) -> list[MatchTask]:
    """Match every pair of a dataset (its official layout, :mod:`pvm_labeler.common.datasets`) into ``out_dir``.

    Every pair's files are checked from their headers (existence, equal sizes) before the first is matched. A pair
    that cannot be read (there, or when decoded: a corrupt or truncated image) is skipped and the others are written;
    then ``out_dir/failures.json`` lists each skipped pair with its reason and an InputError names the first. A run
    with no such pair removes an earlier run's failures.json. A progress bar over pairs goes to stderr (off when
    ``quiet`` or stderr is no TTY). Returns the written tasks (``.paths``) in completion order.

    Raises:
        InputError: no pairs found, or some pairs could not be read (after the others were written).
    """
    refs = discover(dataset, root, split=split, **(reader_options or {}))[:limit]
    failed: dict[str, str] = {}
    readable = []
    for ref in refs:
        try:
            check_pair_sizes(ref)
        except PVMError as exc:
            logger.warning("skipped %s: %s", ref.frame_id, exc)
            failed[ref.frame_id] = str(exc)
        else:
            readable.append(ref)
    jobs = max(1, min(jobs, len(readable)))
    threads = numba_threads_per_worker(jobs)
    tasks = [MatchTask(ref, Path(out_dir), tuple(formats), max_disp, fill, threads) for ref in readable]
    done = []
    with progress.progress_bar(len(refs), len(failed), quiet, desc="pvm-label match") as bar:
        for task in run_tasks(_match_task, tasks, "loky", jobs):
            if task.error is None:
                done.append(task)
            else:
                logger.warning("skipped %s: %s", task.ref.frame_id, task.error)
                failed[task.ref.frame_id] = task.error
            bar.update(1)
    record_failures(Path(out_dir), {ref.frame_id: failed[ref.frame_id] for ref in refs if ref.frame_id in failed},
                    len(refs))
    return done

