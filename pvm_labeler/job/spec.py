"""What one labeling run is asked to do (JobSpec), and the pre-flight check of its pairs from file headers."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pvm_labeler import multiscale
from pvm_labeler.common.datasets import DATASETS, PairRef, check_pair_sizes
from pvm_labeler.common.datasets.refs import META_FILES
from pvm_labeler.common.errors import SKIP_UNUSABLE_HINT, ConfigError, InputError
from pvm_labeler.config import LabelerConfig
from pvm_labeler.packgt import PACK_GT_LABELER
from pvm_labeler.parallel import BACKENDS
from pvm_labeler.shards import COMPRESSIONS, DEFAULT_COMPRESSION

DEFAULT_LABELER = "pvm_labeler.multiscale:label_pair"


@dataclass(frozen=True)
class JobSpec:
    """Everything one labeling run needs (the CLI builds it from flags and ``--config`` YAML).

    Attributes:
        dataset: one of :data:`pvm_labeler.common.datasets.DATASETS`.
        root: dataset folder (None for ``sample``).
        out: shard output directory.
        config: PVM labeler config.
        split: ``training`` or ``testing``.
        dataset_options: reader options (``folder``: left/right/gt globs, gt_scale; ``sceneflow``: pass_).
        limit: label only the first N pairs (sorted by frame id).
        jobs: parallel workers.
        backend: ``loky``, ``threading`` or ``dask``.
        scheduler: Dask scheduler address (``--backend dask``); None starts a local cluster of ``jobs`` workers.
        shard_size: pairs per shard (the unit of parallel work and of resume).
        resume: skip shards that are already complete (default); False relabels every shard.
        overwrite: delete this job's existing files in ``out`` first (needed when the config changed).
        quiet: no progress bar.
        compression: shard compression, one of shards.COMPRESSIONS (``blosc-lz4`` by default).
        numba_threads: threads per worker (default: cores // jobs, at least 1).
        label_fn: ``module:function`` with label_pair's signature (tests inject small fakes here).
        skip_unusable: pairs the pre-flight check refuses (missing or unreadable files, sizes) are left out and
            listed in OUT/failures.json (the job exits 1), instead of stopping the job before anything is written.
    """

    dataset: str
    root: Path | None
    out: Path
    config: LabelerConfig = field(default_factory=LabelerConfig)
    split: str = "training"
    dataset_options: dict[str, Any] = field(default_factory=dict)
    limit: int | None = None
    jobs: int = 1
    backend: str = "loky"
    scheduler: str | None = None
    shard_size: int = 2
    resume: bool = True
    overwrite: bool = False
    quiet: bool = False
    compression: str = DEFAULT_COMPRESSION
    numba_threads: int | None = None
    label_fn: str = DEFAULT_LABELER
    skip_unusable: bool = False

    def __post_init__(self) -> None:
        if self.label_fn == PACK_GT_LABELER:  # no labeler runs: its options change nothing (pack-gt --k 3's shards
            object.__setattr__(self, "config", LabelerConfig(extra=dict(self.config.extra)))  # were refused by the
            # same run without --k)

    def validate(self) -> JobSpec:
        """Raise ConfigError naming the option for out-of-range values; returns self."""
        if self.dataset not in DATASETS:
            raise ConfigError(f"unknown dataset '{self.dataset}' (--dataset); expected one of {', '.join(DATASETS)}")
        self.config.validate()
        if self.config.k < 2:
            raise ConfigError(f"--k must be >= 2 for pyramid voting (K = 1 has nothing to vote), got {self.config.k}")
        if self.limit is not None and self.limit < 1:
            raise ConfigError(f"--limit must be >= 1, got {self.limit}")
        if self.jobs < 1:
            raise ConfigError(f"--jobs must be >= 1, got {self.jobs}")
        if self.shard_size < 1:
            raise ConfigError(f"--shard-size must be >= 1, got {self.shard_size}")
        if self.backend not in BACKENDS:
            raise ConfigError(f"--backend must be one of {', '.join(BACKENDS)}, got '{self.backend}'")
        if self.scheduler is not None and self.backend != "dask":
            raise ConfigError(f"--scheduler needs --backend dask, got --backend {self.backend}")
        if self.compression not in COMPRESSIONS:
            raise ConfigError(f"--compression must be one of {', '.join(COMPRESSIONS)}, got '{self.compression}'")
        if self.numba_threads is not None and self.numba_threads < 1:
            raise ConfigError(f"--numba-threads must be >= 1, got {self.numba_threads}")
        return self

    def dataset_info(self) -> dict[str, Any]:
        """Dataset identity recorded in job.json / index.json (compared on resume)."""
        return {
            "name": self.dataset,
            "root": None if self.root is None else str(Path(self.root).resolve()),
            "split": self.split,
            "options": {k: str(v) for k, v in sorted(self.dataset_options.items())},
            "limit": self.limit,
        }

    def resolved(self) -> dict[str, Any]:
        """The resolved run configuration written to ``config.yaml`` (loadable again with ``--config``, from any
        directory: its paths are absolute; as typed, they named nothing from another working directory)."""
        return {
            "dataset": self.dataset,
            "root": None if self.root is None else str(Path(self.root).resolve()),
            "out": str(Path(self.out).resolve()),
            "split": self.split,
            "dataset_options": {k: str(v) for k, v in self.dataset_options.items()},
            "limit": self.limit,
            "jobs": self.jobs,
            "backend": self.backend,
            "scheduler": self.scheduler,
            "shard_size": self.shard_size,
            "compression": self.compression,
            "numba_threads": self.numba_threads,
            "skip_unusable": self.skip_unusable,
            "labeler": self.config.to_dict(),
        }


def _check_frame_size(height: int, width: int, cfg: LabelerConfig, frame_id: str) -> list[tuple[int, int, float, int]]:
    """The PVM core's "image too small for K and max_disp" check, from the image size alone; returns the frame's
    pyramid geometry (``multiscale.scale_geometry``)."""
    if cfg.max_disp >= width:
        raise InputError(f"--max-disp {cfg.max_disp} must be smaller than the image width {width}")
    eps = multiscale.draw_eps(cfg.seed, frame_id, cfg.k)
    geometry = multiscale.scale_geometry(height, width, eps, cfg.max_disp)
    multiscale.check_sizes(height, width, geometry, cfg)
    return geometry


def preflight(refs: list[PairRef], cfg: LabelerConfig, matcher: bool = True,
              skip: bool = False) -> tuple[dict[str, int], list[dict[str, Any]]]:
    """Check every pair from file headers before anything is written. ``matcher`` False (a GT pack: no matching)
    checks the files and sizes only, not the pyramid's needs.

    Returns:
        ({frame_id: predicted work} of every usable pair (:func:`predicted_work`, used to order the shards; the pixel
        count without the matcher), the unusable pairs as failure records ({frame_id, error, type, files, stage:
        "preflight"}; only with ``skip``)).

    Raises:
        InputError: listing every unusable pair, unless ``skip``; with ``skip``, when no pair is usable.
    """
    problems: list[tuple[PairRef, InputError]] = []
    work = {}
    for ref in refs:
        try:
            height, width = check_pair_sizes(ref)
            work[ref.frame_id] = (predicted_work(_check_frame_size(height, width, cfg, ref.frame_id)) if matcher
                                  else height * width)
        except InputError as exc:
            problems.append((ref, exc))
    if problems and (not skip or not work):
        lines = [f"{ref.frame_id}: {exc}" for ref, exc in problems[:20]]
        more = f"\n  ... and {len(problems) - 20} more" if len(problems) > 20 else ""
        hint = "" if skip else SKIP_UNUSABLE_HINT
        raise InputError(f"{len(problems)} of {len(refs)} pairs are unusable (nothing was written{hint}):\n  "
                         + "\n  ".join(lines) + more)
    unusable = [{"frame_id": ref.frame_id, "error": str(exc), "type": type(exc).__name__, "files": ref.to_dict(),
                 "stage": "preflight"} for ref, exc in problems]
    return work, unusable


def predicted_work(geometry: list[tuple[int, int, float, int]]) -> int:
    """Cost-volume cells of one pair's PVM label, sum over the K scales of h_k * w_k * D_k (a relative cost).

    The pyramid's random factors make pairs of one size differ in cost (KITTI: 0.44 to 0.71 s of CPU): the
    k = 2 scale alone ranges from 1/27 to nearly all of the full-resolution cost.
    """
    return sum(multiscale.scale_cells(scale) for scale in geometry)


def absolute_paths(ref: PairRef) -> PairRef:
    """A copy of ``ref`` whose file paths (and meta file entries) are absolute; synthetic pairs are unchanged."""
    if ref.meta.get("synthetic"):
        return ref
    files = {name: None if getattr(ref, name) is None else Path(getattr(ref, name)).resolve()
             for name in ("left", "right", "gt", "gt_noc", "gt_right")}
    meta = {k: str(Path(v).resolve()) if k in META_FILES else v for k, v in ref.meta.items()}
    return dataclasses.replace(ref, meta=meta, **files)
