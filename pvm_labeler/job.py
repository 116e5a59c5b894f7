"""The labeling job: dataset in, versioned HDF5 shards out; resumable, parallel (joblib or Dask).

``run(spec)`` does, in order:

1. validate the options and the labeler config (nothing is written before every check passed);
2. discover the pairs and pre-flight them from file headers (missing/unreadable files, left/right/GT size
   mismatches, images too small for K and max_disp): ALL problems are reported at once, naming the files;
3. check the output directory: writable; existing shards must come from the same job (config, dataset, shard
   plan) unless ``overwrite``; ``job.json`` (the plan) and ``config.yaml`` (the resolved config) are written;
4. label the shards that are not complete yet (a shard is complete when its final file exists, opens, has the
   same config and plan and every array reads back), one task per shard, streaming results back;
5. write ``failures.json`` if single pairs failed, then ``index.json`` last (atomically).

Shards are assigned deterministically (sorted frame ids, ``shard_size`` per shard) and every frame's labels depend
only on (config, frame id, pixels), so labels are identical for any ``jobs`` and backend, and a run killed at any
point and restarted finishes only the missing shards with the same result.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import json
import logging
import math
import os
import queue
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from pvm_labeler import multiscale
from pvm_labeler.common.atomic import atomic_write_text
from pvm_labeler.common.datasets import DATASETS, PairRef, check_pair_sizes, discover, load_pair
from pvm_labeler.common.errors import ConfigError, InputError, PVMError, ShardError
from pvm_labeler.common.metrics import MetricAccumulator
from pvm_labeler.config import LabelerConfig
from pvm_labeler.parallel import (
    BACKENDS,
    CoreTokens,
    SpareCores,
    available_cores,
    numba_threads_per_worker,
    peak_rss_mb,
    reset_peak_rss,
    run_tasks,
    thread_budget,
)
from pvm_labeler.shards import (
    COMPRESSIONS,
    DEFAULT_COMPRESSION,
    INDEX_NAME,
    TMP_SUFFIX,
    ShardRecord,
    ShardWriter,
    open_shard,
    shard_name,
    shard_sample_ids,
    verify_shard,
    write_index,
)

logger = logging.getLogger(__name__)

JOB_FILE = "job.json"
CONFIG_FILE = "config.yaml"
FAILURES_FILE = "failures.json"
DEFAULT_LABELER = "pvm_labeler.multiscale:label_pair"
#: Files the job owns in its output directory (``overwrite`` deletes exactly these, nothing else).
OWNED_GLOBS: tuple[str, ...] = ("shard-*.h5", f"shard-*.h5{TMP_SUFFIX}", INDEX_NAME, JOB_FILE, CONFIG_FILE,
                                FAILURES_FILE) + tuple(f"{name}.*.tmp" for name in (INDEX_NAME, JOB_FILE, CONFIG_FILE,
                                                                                    FAILURES_FILE))


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
        """The resolved run configuration written to ``config.yaml`` (loadable again with ``--config``)."""
        return {
            "dataset": self.dataset,
            "root": None if self.root is None else str(self.root),
            "out": str(self.out),
            "split": self.split,
            "dataset_options": {k: str(v) for k, v in self.dataset_options.items()},
            "limit": self.limit,
            "jobs": self.jobs,
            "backend": self.backend,
            "scheduler": self.scheduler,
            "shard_size": self.shard_size,
            "compression": self.compression,
            "numba_threads": self.numba_threads,
            "labeler": self.config.to_dict(),
        }


@dataclass
class ShardTask:
    """One unit of parallel work: label ``refs`` and write them into shard ``index`` (picklable)."""

    index: int
    path: str
    refs: list[PairRef]
    config: dict[str, Any]
    compression: str
    numba_threads: int
    label_fn: str = DEFAULT_LABELER
    progress: Any = None  # queue-like: the worker puts 1 per finished pair (progress bar); None = no reporting
    core_tokens: CoreTokens | None = None  # the machine's cores shared by the job's workers (parallel.CoreTokens)


@dataclass
class ShardOutcome:
    """What a worker reports back about its shard."""

    index: int
    file: str
    sample_ids: list[str]
    planned: list[str]
    failures: list[dict[str, Any]]
    stats: dict[str, Any]
    seconds: float
    peak_rss_mb: float
    pid: int
    resumed: bool = False
    cpu_seconds: float = 0.0


@dataclass
class JobSummary:
    """End-of-run summary (also stored in index.json under "summary")."""

    out: str
    pairs_total: int
    pairs_labeled: int
    pairs_failed: int
    shards_total: int
    shards_written: int
    shards_resumed: int
    seconds: float
    pairs_per_s: float
    label_fraction: float  # % of all image pixels that received a label
    metrics: dict[str, float] | None  # labels vs the most complete GT, pooled over pixels
    metrics_noc: dict[str, float] | None  # labels vs non-occluded GT where known
    peak_rss_mb_per_worker: float
    cpu_seconds_per_pair: float  # worker CPU time (all threads) per labelled pair: load-independent cost
    parallel: dict[str, Any]
    failures: list[dict[str, Any]]

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def format(self) -> str:
        """Human-readable multi-line summary."""
        lines = [
            f"labelled {self.pairs_labeled}/{self.pairs_total} pairs into {self.out} "
            f"({self.shards_written} shards written, {self.shards_resumed} resumed) in {self.seconds:.1f} s "
            f"({self.pairs_per_s:.2f} pairs/s, peak RSS per worker {self.peak_rss_mb_per_worker:.0f} MiB)",
            f"label density: {self.label_fraction:.1f} % of all pixels",
        ]
        for name, m in (("GT", self.metrics), ("GT noc", self.metrics_noc)):
            if m and m.get("n_valid"):
                lines.append(
                    f"vs {name}: density {m['density']:.1f} % of GT-valid pixels, bad-1 {m['bad1']:.2f} %, "
                    f"bad-3 {m['bad3']:.2f} %, AEPE {m['epe']:.3f} px, D1 {m['d1']:.2f} %"
                )
        if self.failures:
            lines.append(f"{len(self.failures)} pairs FAILED (see {Path(self.out) / FAILURES_FILE}):")
            lines += [f"  {f['frame_id']}: {f['error']}" for f in self.failures[:10]]
        return "\n".join(lines)


# ----------------------------------------------------------------------------------------------------- worker
def _resolve_labeler(name: str) -> Callable[..., Any]:
    module, _, attr = name.partition(":")
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        raise ConfigError(f"labeler '{name}' cannot be imported: {exc}") from exc


def _acc_dict(acc: MetricAccumulator) -> dict[str, Any]:
    return asdict(acc)


def _record_for(ref: PairRef, cfg: LabelerConfig, labeler: Callable[..., Any]) -> tuple[ShardRecord, dict[str, Any]]:
    sample = load_pair(ref)
    t0 = time.perf_counter()
    result = labeler(sample.left, sample.right, cfg, ref.frame_id)
    seconds = time.perf_counter() - t0
    frame_metrics: dict[str, Any] = {
        "label_fraction": float(100.0 * np.isfinite(result.label).mean()),
        "seconds": seconds,
    }
    attrs = {
        "sources": sample.sources,
        "eps": np.asarray(result.eps, dtype=np.float64),
        "factors": np.asarray(result.factors, dtype=np.float64),
        "seed": int(cfg.seed),
        "timings": {k: float(v) for k, v in result.timings.items()},
        "height": int(sample.left.shape[0]),
        "width": int(sample.left.shape[1]),
    }
    if sample.max_disp is not None:
        attrs["dataset_max_disp"] = int(sample.max_disp)
    record = ShardRecord(
        frame_id=ref.frame_id,
        left=sample.left,
        right=sample.right,
        label=np.asarray(result.label, dtype=np.float32),
        label_right=np.asarray(result.label_right, dtype=np.float32),
        confidence=np.asarray(result.confidence, dtype=np.float32),
        gt=sample.gt,
        gt_noc=sample.gt_noc,
        gt_right=sample.gt_right,
        attrs=attrs,
    )
    return record, frame_metrics


def _report_pair(task: ShardTask) -> None:
    if task.progress is not None:
        try:
            task.progress.put(1)
        except (OSError, EOFError) as exc:  # the parent's manager is gone: progress is cosmetic, labels are not
            logger.debug("progress queue unavailable: %s", exc)
            task.progress = None


def label_shard(task: ShardTask) -> ShardOutcome:
    """Worker entry: label every pair of one shard and publish the shard file atomically.

    Single-pair failures (bad files, sizes, labeler input errors) are recorded and the rest of the shard goes on.
    A shard in which every pair failed is not published (a resume will retry it).
    """
    t0, c0 = time.perf_counter(), time.process_time()
    reset_peak_rss()  # the reported peak is this shard's (an in-process --jobs 1 may have done other work before)
    cfg = LabelerConfig.from_dict(task.config)
    labeler = _resolve_labeler(task.label_fn)
    failures: list[dict[str, Any]] = []
    acc, acc_noc = MetricAccumulator(), MetricAccumulator()
    labelled_px = total_px = 0
    path = Path(task.path)
    planned = [ref.frame_id for ref in task.refs]
    with thread_budget(task.numba_threads, task.core_tokens):
        writer = ShardWriter(path, task.config, compression=task.compression, extra_attrs={"planned": planned})
        try:
            for ref in task.refs:
                try:
                    record, frame = _record_for(ref, cfg, labeler)
                except (PVMError, OSError, ValueError) as exc:
                    logger.error("pair %s failed: %s", ref.frame_id, exc)
                    failures.append({"frame_id": ref.frame_id, "error": str(exc), "type": type(exc).__name__,
                                     "files": ref.to_dict()})
                    _report_pair(task)
                    continue
                if record.gt is not None:
                    frame["gt"] = acc.update(record.label, record.gt)
                if record.gt_noc is not None:
                    frame["gt_noc"] = acc_noc.update(record.label, record.gt_noc)
                labelled_px += int(np.isfinite(record.label).sum())
                total_px += record.label.size
                record.attrs["metrics"] = frame
                writer.add(record)
                _report_pair(task)
            stats = {"acc": _acc_dict(acc), "acc_noc": _acc_dict(acc_noc), "labelled_px": labelled_px,
                     "total_px": total_px, "failures": failures}
            writer.set_attr("stats", json.dumps(stats))
            ids = writer.sample_ids
            if ids:
                writer.close()
            else:
                writer.abort()
        except BaseException:
            writer.abort()
            raise
    return ShardOutcome(index=task.index, file=path.name, sample_ids=ids, planned=planned, failures=failures,
                        stats=stats, seconds=time.perf_counter() - t0, peak_rss_mb=peak_rss_mb(), pid=os.getpid(),
                        cpu_seconds=time.process_time() - c0)


# ------------------------------------------------------------------------------------------------- pre-flight
def _check_frame_size(height: int, width: int, cfg: LabelerConfig, frame_id: str) -> list[tuple[int, int, float, int]]:
    """The PVM core's "image too small for K and max_disp" check, from the image size alone; returns the frame's
    pyramid geometry (``multiscale.scale_geometry``)."""
    if cfg.max_disp >= width:
        raise InputError(f"--max-disp {cfg.max_disp} must be smaller than the image width {width}")
    eps = multiscale.draw_eps(cfg.seed, frame_id, cfg.k)
    geometry = multiscale.scale_geometry(height, width, eps, cfg.max_disp)
    multiscale.check_sizes(height, width, geometry, cfg)
    return geometry


def preflight(refs: list[PairRef], cfg: LabelerConfig) -> dict[str, int]:
    """Check every pair from file headers before anything is written; raise one InputError listing all problems.

    Returns:
        {frame_id: predicted work} of every pair (:func:`predicted_work`, used to order the shards).
    """
    problems = []
    work = {}
    for ref in refs:
        try:
            height, width = check_pair_sizes(ref)
            work[ref.frame_id] = predicted_work(_check_frame_size(height, width, cfg, ref.frame_id))
        except InputError as exc:
            problems.append(f"{ref.frame_id}: {exc}")
    if problems:
        more = f"\n  ... and {len(problems) - 20} more" if len(problems) > 20 else ""
        raise InputError(f"{len(problems)} of {len(refs)} pairs are unusable (nothing was written):\n  "
                         + "\n  ".join(problems[:20]) + more)
    return work


def predicted_work(geometry: list[tuple[int, int, float, int]]) -> int:
    """Cost-volume cells of one pair's PVM label, sum over the K scales of h_k * w_k * D_k (a relative cost).

    The pyramid's random factors make pairs of one size differ in cost (KITTI: 0.44 to 0.71 s of CPU): the
    k = 2 scale alone ranges from 1/27 to nearly all of the full-resolution cost.
    """
    return sum(multiscale.scale_cells(scale) for scale in geometry)


def _longest_first(tasks: list[ShardTask], work: dict[str, int]) -> list[ShardTask]:
    """Tasks in descending predicted work: the cheapest shards run last, so workers finish close together
    (longest-processing-time-first scheduling). Shard files and labels do not depend on the order."""
    return sorted(tasks, key=lambda task: sum(work[ref.frame_id] for ref in task.refs), reverse=True)


# ----------------------------------------------------------------------------------------------- output dir
def _check_writable(out: Path) -> None:
    probe_dir = out
    while not probe_dir.exists():
        probe_dir = probe_dir.parent
    if not probe_dir.is_dir():
        raise InputError(f"output dir not writable: --out {out} ({probe_dir} is a file, not a directory)")
    try:
        with tempfile.TemporaryFile(dir=probe_dir):
            pass
    except OSError as exc:
        raise InputError(f"output dir not writable: --out {out} ({probe_dir}: {exc.strerror})") from exc


def _plan(refs: list[PairRef], shard_size: int) -> list[list[PairRef]]:
    return [refs[i : i + shard_size] for i in range(0, len(refs), shard_size)]


def _job_doc(spec: JobSpec, plan: list[list[PairRef]]) -> dict[str, Any]:
    return {
        "config": json.loads(spec.config.to_json()),
        "dataset": spec.dataset_info(),
        "shard_size": spec.shard_size,
        "compression": spec.compression,
        "plan": [[ref.frame_id for ref in shard] for shard in plan],
    }


def _identity(job_doc: dict[str, Any]) -> dict[str, Any]:
    """What must match for existing shards to be reusable: config, dataset, shard size, compression.

    The plan and --limit may change (e.g. a quick --limit 4 run, then the whole dataset): every shard is
    re-checked against its own planned frame ids, so shards whose frames did not change are kept.
    """
    doc = {k: v for k, v in job_doc.items() if k != "plan"}
    doc["dataset"] = {k: v for k, v in job_doc.get("dataset", {}).items() if k != "limit"}
    return doc


def _diff(old: dict[str, Any], new: dict[str, Any], prefix: str = "") -> list[str]:
    out = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            out += _diff(a, b, f"{prefix}{key}.")
        elif a != b:
            text_a, text_b = json.dumps(a)[:60], json.dumps(b)[:60]
            out.append(f"{prefix}{key}: {text_a} -> {text_b}")
    return out


def _owned_files(out: Path) -> list[Path]:
    return sorted({p for pattern in OWNED_GLOBS for p in out.glob(pattern)})


def _prepare_out(spec: JobSpec, job_doc: dict[str, Any]) -> None:
    out = spec.out
    _check_writable(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} is a file, expected a directory")
    owned = _owned_files(out) if out.is_dir() else []
    if owned and spec.overwrite:
        logger.info("--overwrite: deleting %d files of a previous run in %s", len(owned), out)
        for path in owned:
            path.unlink()
    elif owned:
        job_path = out / JOB_FILE
        if not job_path.is_file():
            raise InputError(f"--out {out} already holds shards from an unknown run (no {JOB_FILE}); "
                             f"pass --overwrite to replace them or choose another --out")
        try:
            old = json.loads(job_path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"cannot read {job_path}: {exc}; pass --overwrite to start afresh") from exc
        changes = _diff(_identity(old), _identity(job_doc))
        if changes:
            # Shards of an older default compression are still good: say how to keep them.
            same_but_compression = _identity({**old, "compression": job_doc["compression"]}) == _identity(job_doc)
            keep = f", or --compression {old['compression']} to continue them" if same_but_compression else ""
            raise InputError(f"existing shards in {out} were made with a different config/dataset ("
                             + "; ".join(changes[:6]) + f"); pass --overwrite to replace them{keep}, "
                             "or choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    # Shards past the end of the plan (an earlier run with a larger --limit) would linger unindexed: remove them.
    for path in out.glob("shard-*.h5"):
        stem = path.name[len("shard-") : -len(".h5")]
        if stem.isdigit() and int(stem) >= len(job_doc["plan"]):
            path.unlink()
    atomic_write_text(out / JOB_FILE, json.dumps(job_doc, indent=2))
    atomic_write_text(out / CONFIG_FILE, yaml.safe_dump(spec.resolved(), sort_keys=False))


def _complete_shard(path: Path, planned: list[str], config: dict[str, Any]) -> ShardOutcome | None:
    """The outcome of an already complete shard (same plan and config, every array readable), else None."""
    if not path.is_file():
        return None
    try:
        with open_shard(path) as h5:
            ids = shard_sample_ids(h5)
            old_planned = json.loads(h5.attrs["planned"])
            stats = json.loads(h5.attrs["stats"])
    except (ShardError, KeyError, ValueError, OSError) as exc:
        logger.warning("shard %s is not reusable (%s); relabelling it", path, exc)
        return None
    if old_planned != planned:
        logger.warning("shard %s holds another plan; relabelling it", path)
        return None
    problems = verify_shard(path, ids, config)
    if problems:
        logger.warning("shard %s is broken (%s); relabelling it", path, problems[0])
        return None
    return ShardOutcome(index=-1, file=path.name, sample_ids=ids, planned=planned, failures=stats["failures"],
                        stats=stats, seconds=0.0, peak_rss_mb=0.0, pid=0, resumed=True)


# ------------------------------------------------------------------------------------------------------- run
_META_PATHS = ("noc_mask", "occlusion", "calib")  # PairRef.meta entries that name files


def absolute_paths(ref: PairRef) -> PairRef:
    """A copy of ``ref`` whose file paths (and meta file entries) are absolute; synthetic pairs are unchanged."""
    if ref.meta.get("synthetic"):
        return ref
    files = {name: None if getattr(ref, name) is None else Path(getattr(ref, name)).resolve()
             for name in ("left", "right", "gt", "gt_noc", "gt_right")}
    meta = {k: str(Path(v).resolve()) if k in _META_PATHS else v for k, v in ref.meta.items()}
    return dataclasses.replace(ref, meta=meta, **files)


def run(spec: JobSpec) -> JobSummary:
    """Run the labeling job described by ``spec`` (see the module docstring).

    Returns:
        JobSummary; ``summary.failures`` lists pairs that failed (the caller decides the exit code).

    Raises:
        ConfigError / InputError: bad options or data, before anything is written.
        ShardError: a shard could not be written.
    """
    t0 = time.perf_counter()
    spec.validate()
    refs = discover(spec.dataset, spec.root, spec.split, **spec.dataset_options)
    if spec.limit is not None:
        refs = refs[: spec.limit]
    work = preflight(refs, spec.config)
    plan = _plan(refs, spec.shard_size)
    job_doc = _job_doc(spec, plan)
    _prepare_out(spec, job_doc)
    config = job_doc["config"]
    out = spec.out

    outcomes: dict[int, ShardOutcome] = {}
    pending: list[ShardTask] = []
    threads = spec.numba_threads or numba_threads_per_worker(spec.jobs)
    for index, shard_refs in enumerate(plan):
        path = out / shard_name(index)
        planned = [ref.frame_id for ref in shard_refs]
        done = _complete_shard(path, planned, config) if spec.resume else None
        if done is not None:
            done.index = index
            outcomes[index] = done
        else:
            path.with_name(path.name + TMP_SUFFIX).unlink(missing_ok=True)  # stale from a killed run
            # Absolute paths: Dask workers may run in another working directory, or on another machine.
            pending.append(ShardTask(index, str(path.resolve()), [absolute_paths(r) for r in shard_refs], config,
                                     spec.compression, threads, spec.label_fn))
    pending = _longest_first(pending, work)
    if pending:
        # An index next to a partial set of shards would look complete to a reader; it is rewritten at the end.
        (out / INDEX_NAME).unlink(missing_ok=True)
    logger.info("%d pairs in %d shards: %d complete, %d to label (%s, %d jobs, %d numba threads each)",
                len(refs), len(plan), len(outcomes), len(pending), spec.backend, spec.jobs, threads)

    bar = _progress(len(refs), sum(len(o.planned) for o in outcomes.values()), spec.quiet)
    with _PairProgress(bar, spec, pending) as per_pair, _spare_cores(spec, threads, pending) as spare:
        running = len(pending)
        for outcome in run_tasks(label_shard, pending, spec.backend, spec.jobs, spec.scheduler):
            outcomes[outcome.index] = outcome
            running -= 1
            if spare is not None:
                spare.outstanding(running)
            if not per_pair.active:
                bar.update(len(outcome.planned))
            bar.set_postfix(shards=f"{len(outcomes)}/{len(plan)}")
    return _finish(spec, refs, plan, outcomes, threads, time.perf_counter() - t0)


@contextlib.contextmanager
def _spare_cores(spec: JobSpec, threads: int, tasks: list[ShardTask]) -> Iterator[SpareCores | None]:
    """Give the tasks one :class:`CoreTokens` when the workers share this machine's cores one each (or more).

    The parent holds the workers' tokens and frees a worker's cores once fewer shards than workers remain: a frame
    still running elsewhere then runs its right views on them (otherwise the last of 15 frames on 2 workers leaves
    one core idle for up to a frame). Not for Dask (workers may sit on other machines), one worker (it owns its
    cores already), or more threads than cores (nothing is spare).
    """
    cores = available_cores()
    local = spec.backend in ("loky", "threading") and spec.jobs > 1
    if not tasks or not local or spec.jobs * threads > cores:
        yield None
        return
    with tempfile.TemporaryDirectory(prefix="pvm-cores-") as directory:
        tokens = CoreTokens(directory, cores)
        for task in tasks:
            task.core_tokens = tokens
        with SpareCores(tokens, spec.jobs, threads) as spare:
            spare.outstanding(len(tasks))  # fewer shards than workers: the surplus workers never start one
            yield spare


class _PairProgress:
    """Advance the bar per finished pair: workers put 1 per pair into a queue that a parent thread drains.

    Only when the bar is shown, and not for Dask (remote workers cannot reach a local queue; the bar then
    advances per shard). loky workers get a multiprocessing Manager queue proxy, threads a plain queue.
    """

    def __init__(self, bar: Any, spec: JobSpec, tasks: list[ShardTask]) -> None:
        self.bar, self.spec, self.tasks = bar, spec, tasks
        self.active = not bar.disable and bool(tasks) and spec.backend != "dask"
        self._manager: Any = None
        self._queue: Any = None
        self._thread: threading.Thread | None = None

    def __enter__(self) -> _PairProgress:
        if self.active:
            if self.spec.jobs > 1 and self.spec.backend == "loky":
                import multiprocessing

                self._manager = multiprocessing.Manager()
                self._queue = self._manager.Queue()
            else:
                self._queue = queue.SimpleQueue()
            for task in self.tasks:
                task.progress = self._queue
            self._thread = threading.Thread(target=self._drain, name="pvm-label-progress", daemon=True)
            self._thread.start()
        return self

    def _drain(self) -> None:
        while (item := self._queue.get()) is not None:
            self.bar.update(item)

    def __exit__(self, *exc: object) -> None:
        try:
            if self._thread is not None:
                self._queue.put(None)  # FIFO: every worker's put happened before its task returned
                self._thread.join(timeout=30)
        finally:
            if self._manager is not None:
                self._manager.shutdown()
            self.bar.close()


def _json_safe(value: Any) -> Any:
    """Replace NaN/inf by None so index.json stays strict JSON (readable outside Python)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_json_safe(v) for v in value]
    return value


def _progress(total: int, initial: int, quiet: bool) -> Any:
    from tqdm import tqdm

    disable = quiet or not sys.stderr.isatty()
    return tqdm(total=total, initial=initial, unit="pair", desc="pvm-label", file=sys.stderr, disable=disable,
                dynamic_ncols=True)


def _finish(spec: JobSpec, refs: list[PairRef], plan: list[list[PairRef]], outcomes: dict[int, ShardOutcome],
            threads: int, seconds: float) -> JobSummary:
    out = spec.out
    acc, acc_noc = MetricAccumulator(), MetricAccumulator()
    labelled_px = total_px = 0
    failures: list[dict[str, Any]] = []
    shards = []
    for index in range(len(plan)):
        outcome = outcomes[index]
        failures += outcome.failures
        if outcome.sample_ids:
            shards.append((outcome.file, outcome.sample_ids))
        acc.merge(MetricAccumulator(**outcome.stats["acc"]))
        acc_noc.merge(MetricAccumulator(**outcome.stats["acc_noc"]))
        labelled_px += outcome.stats["labelled_px"]
        total_px += outcome.stats["total_px"]
    written = [o for o in outcomes.values() if not o.resumed]
    labeled = sum(len(ids) for _, ids in shards)
    work_pairs = sum(len(o.planned) for o in written)
    summary = JobSummary(
        out=str(out),
        pairs_total=len(refs),
        pairs_labeled=labeled,
        pairs_failed=len(failures),
        shards_total=len(plan),
        shards_written=sum(1 for o in written if o.sample_ids),
        shards_resumed=sum(1 for o in outcomes.values() if o.resumed),
        seconds=seconds,
        pairs_per_s=work_pairs / seconds if seconds > 0 else math.nan,
        label_fraction=100.0 * labelled_px / total_px if total_px else math.nan,
        metrics=acc.compute() if acc.n_frames else None,
        metrics_noc=acc_noc.compute() if acc_noc.n_frames else None,
        peak_rss_mb_per_worker=max((o.peak_rss_mb for o in written), default=0.0),
        cpu_seconds_per_pair=sum(o.cpu_seconds for o in written) / work_pairs if work_pairs else math.nan,
        parallel={"backend": spec.backend, "jobs": spec.jobs, "numba_threads_per_worker": threads,
                  "scheduler": spec.scheduler},
        failures=failures,
    )
    if failures:
        atomic_write_text(out / FAILURES_FILE, json.dumps(failures, indent=2))
    else:
        (out / FAILURES_FILE).unlink(missing_ok=True)
    write_index(out, shards, json.loads(spec.config.to_json()), spec.dataset_info(),
                extra={"summary": _json_safe(summary.to_dict()), "compression": spec.compression})
    return summary
