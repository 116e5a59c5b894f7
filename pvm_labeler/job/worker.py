"""The worker side of the job: label every pair of one shard and publish the shard file (one task = one shard)."""

from __future__ import annotations

import importlib
import inspect
import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pvm_labeler.common.datasets import PairRef, check_pair_sizes, load_pair
from pvm_labeler.common.errors import ConfigError, PVMError
from pvm_labeler.common.metrics import MetricAccumulator
from pvm_labeler.config import LabelerConfig
from pvm_labeler.job.spec import DEFAULT_LABELER
from pvm_labeler.parallel import peak_rss_mb, reset_peak_rss, thread_budget
from pvm_labeler.shards import ShardRecord, ShardWriter
from pvm_labeler.shards.writer import expected_shard_bytes
from pvm_labeler.stages import count_stages

logger = logging.getLogger(__name__)


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


def _resolve_labeler(name: str) -> Callable[..., Any]:
    module, _, attr = name.partition(":")
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        raise ConfigError(f"labeler '{name}' cannot be imported: {exc}") from exc


def _record_for(ref: PairRef, cfg: LabelerConfig, labeler: Callable[..., Any]) -> tuple[ShardRecord, dict[str, Any]]:
    """Load and label one pair; returns its shard record and its per-frame metrics (label fraction, seconds)."""
    sample = load_pair(ref)
    t0 = time.perf_counter()
    gt = sample.gt_noc if sample.gt_noc is not None else sample.gt  # the evaluator's GT rule
    # The stage breakdown costs one more vote pass: only where GT will score it, and only for labelers that offer it.
    extra = {"with_stages": True} if gt is not None and "with_stages" in inspect.signature(labeler).parameters else {}
    result = labeler(sample.left, sample.right, cfg, ref.frame_id, **extra)
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
    if gt is not None and getattr(result, "stages", None) is not None:
        attrs["stages"] = count_stages(*result.stages, gt)  # the vote table of `pvm-label report`
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


def _failure(ref: PairRef, exc: Exception) -> dict[str, Any]:
    logger.error("pair %s failed: %s", ref.frame_id, exc)
    return {"frame_id": ref.frame_id, "error": str(exc), "type": type(exc).__name__, "files": ref.to_dict()}


def _label_into(task: ShardTask, writer: ShardWriter) -> dict[str, Any]:
    """Label the task's pairs into ``writer``; returns the shard's stats (GT accumulators, pixels, failures)."""
    cfg = LabelerConfig.from_dict(task.config)
    labeler = _resolve_labeler(task.label_fn)
    failures: list[dict[str, Any]] = []
    acc, acc_noc = MetricAccumulator(), MetricAccumulator()
    labelled_px = total_px = 0
    for ref in task.refs:
        try:
            record, frame = _record_for(ref, cfg, labeler)
        except (PVMError, OSError, ValueError) as exc:
            failures.append(_failure(ref, exc))
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
    return {"acc": asdict(acc), "acc_noc": asdict(acc_noc), "labelled_px": labelled_px, "total_px": total_px,
            "failures": failures}


def _expected_bytes(task: ShardTask) -> int:
    """The shard's expected size on disk, from its pairs' image headers (checked before any pair is labelled)."""
    pixels = 0
    for ref in task.refs:
        try:
            height, width = check_pair_sizes(ref)
        except (PVMError, OSError):  # an unreadable pair is recorded as a failure when it is labelled
            continue
        pixels += height * width
    return expected_shard_bytes(pixels, any(ref.gt is not None for ref in task.refs), task.compression)


def label_shard(task: ShardTask) -> ShardOutcome:
    """Worker entry: label every pair of one shard and publish the shard file atomically.

    Single-pair failures (bad files, sizes, labeler input errors) are recorded and the rest of the shard goes on.
    A shard in which every pair failed is not published, and an older file of that shard is removed (a resume
    retries it, as it retries the failed pairs of a published shard).
    """
    t0, c0 = time.perf_counter(), time.process_time()
    reset_peak_rss()  # the reported peak is this shard's (an in-process --jobs 1 may have done other work before)
    path = Path(task.path)
    planned = [ref.frame_id for ref in task.refs]
    with thread_budget(task.numba_threads):
        # what each planned pair's files were when labelled: a resume relabels a shard whose images changed
        sources = {ref.frame_id: ref.source_digest() for ref in task.refs}
        writer = ShardWriter(path, task.config, compression=task.compression,
                             extra_attrs={"planned": planned, "source_digests": sources},
                             expected_bytes=_expected_bytes(task))
        try:
            stats = _label_into(task, writer)
            writer.set_attr("stats", json.dumps(stats))
            ids = writer.sample_ids
            if ids:
                writer.close()  # replaces an older shard of the same index atomically
            else:
                writer.abort()
                path.unlink(missing_ok=True)  # an older shard of this index (a retry that failed again) is stale
        except BaseException:
            writer.abort()
            raise
    return ShardOutcome(index=task.index, file=path.name, sample_ids=ids, planned=planned,
                        failures=stats["failures"], stats=stats, seconds=time.perf_counter() - t0,
                        peak_rss_mb=peak_rss_mb(), pid=os.getpid(), cpu_seconds=time.process_time() - c0)
