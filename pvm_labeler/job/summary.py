"""The end of a run: pool the shards' statistics into a JobSummary, write failures.json and index.json (last)."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from pvm_labeler.common.atomic import atomic_write_text, json_safe, read_failures
from pvm_labeler.common.datasets import PairRef
from pvm_labeler.common.errors import counted
from pvm_labeler.common.metrics import MetricAccumulator
from pvm_labeler.job.outdir import FAILURES_FILE
from pvm_labeler.job.spec import JobSpec
from pvm_labeler.job.worker import ShardOutcome
from pvm_labeler.packgt import PACK_GT_LABELER
from pvm_labeler.shards import write_index


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
    gt_only: bool = False  # a GT pack (pvm-label pack-gt): images + GT, no labels
    gt_fraction: float = math.nan  # % of all image pixels with valid GT
    gt_warnings: list[str] = field(default_factory=list)  # the GT check of the first pair with GT: its problems

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def format(self) -> str:
        """Human-readable multi-line summary (a GT pack's: pairs packed and GT density, no label lines)."""
        done = "packed" if self.gt_only else "labelled"
        if self.shards_total and self.shards_resumed == self.shards_total:  # no pair was worked on by this run
            head = (f"nothing to do: all {counted(self.pairs_labeled, 'pair')} in {self.out} were already {done} "
                    f"({counted(self.shards_resumed, 'shard')} resumed, checked in {self.seconds:.1f} s)")
        else:
            speed = (f" ({self.pairs_per_s:.2f} pairs/s, peak RSS per worker {self.peak_rss_mb_per_worker:.0f} MiB)"
                     if self.pairs_per_s > 0 else "")  # NaN or 0: no pair was worked on, nothing to time
            what = " (images + GT, no labels)" if self.gt_only else ""
            head = (f"{done} {self.pairs_labeled}/{counted(self.pairs_total, 'pair')}{what} into {self.out} "
                    f"({counted(self.shards_written, 'shard')} written, {self.shards_resumed} resumed) in "
                    f"{self.seconds:.1f} s{speed}")
        if self.gt_only:  # no labels: label density and errors vs GT would read as a failure (0 %, NaN)
            lines = [head, f"GT density: {self.gt_fraction:.1f} % of all pixels"]
        else:
            lines = [head, f"label density: {self.label_fraction:.1f} % of all pixels"]
            lines += [f"vs {name}: density {m['density']:.1f} % of GT-valid pixels, bad-1 {m['bad1']:.2f} %, "
                      f"bad-3 {m['bad3']:.2f} %, AEPE {m['epe']:.3f} px, D1 {m['d1']:.2f} %"
                      for name, m in (("GT", self.metrics), ("GT noc", self.metrics_noc)) if m and m.get("n_valid")]
        if self.gt_warnings:
            lines.append("WARNING: the GT looks wrong, so the numbers against it are likely meaningless:")
            lines += [f"  {warning}" for warning in self.gt_warnings]
        if self.failures:
            lines.append(f"{counted(len(self.failures), 'pair')} FAILED (see {Path(self.out) / FAILURES_FILE}; a "
                         "re-run retries them):")
            lines += [f"  {f['frame_id']}: {f['error']}" for f in self.failures[:10]]
        return "\n".join(lines)


def _pooled(outcomes: list[ShardOutcome]) -> tuple[MetricAccumulator, MetricAccumulator, int, int]:
    """GT accumulators (all, noc) and labelled / total pixels summed over the shards."""
    acc, acc_noc = MetricAccumulator(), MetricAccumulator()
    labelled_px = total_px = 0
    for outcome in outcomes:
        acc.merge(MetricAccumulator(**outcome.stats["acc"]))
        acc_noc.merge(MetricAccumulator(**outcome.stats["acc_noc"]))
        labelled_px += outcome.stats["labelled_px"]
        total_px += outcome.stats["total_px"]
    return acc, acc_noc, labelled_px, total_px


def finish(spec: JobSpec, refs: list[PairRef], plan: list[list[PairRef]], outcomes: dict[int, ShardOutcome],
           threads: int, seconds: float, gt_warnings: list[str] | None = None,
           unusable: list[dict[str, Any]] | None = None) -> JobSummary:
    """Summarise the run, write (or remove) failures.json, and write index.json last. ``gt_warnings``: the GT
    check's lines (``datasets.first_gt_problems``), repeated in the summary. ``unusable``: the pairs the pre-flight
    check left out (``--skip-unusable``), failures ahead of the labelling's; ``refs`` holds the others."""
    ordered = [outcomes[index] for index in range(len(plan))]
    unusable = list(unusable or [])
    failures = unusable + [failure for outcome in ordered for failure in outcome.failures]
    shards = [(o.file, o.sample_ids) for o in ordered if o.sample_ids]
    acc, acc_noc, labelled_px, total_px = _pooled(ordered)
    written = [o for o in outcomes.values() if not o.resumed]
    work_pairs = sum(len(o.sample_ids) for o in written)  # labelled now: a failed pair is no throughput
    summary = JobSummary(
        out=str(spec.out),
        pairs_total=len(refs) + len(unusable),
        pairs_labeled=sum(len(ids) for _, ids in shards),
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
        gt_only=spec.label_fn == PACK_GT_LABELER,
        gt_fraction=100.0 * acc.n_valid / total_px if total_px else math.nan,
        gt_warnings=list(gt_warnings or []),
    )
    if failures:
        atomic_write_text(spec.out / FAILURES_FILE, json.dumps(failures, indent=2))
    else:
        (spec.out / FAILURES_FILE).unlink(missing_ok=True)
    write_index(spec.out, shards, json.loads(spec.config.to_json()), spec.dataset_info(),
                extra={"summary": json_safe(summary.to_dict()), "compression": spec.compression})
    return summary


def failures_lines(out: Path, labelled: int, limit: int = 5) -> list[str]:
    """What `pvm-label verify` prints about the pairs a run could not label ([] when none failed).

    Args:
        out: the shard directory.
        labelled: samples in its shards (the failed pairs are not among them).
        limit: failed pairs listed by id and reason.
    """
    failures = read_failures(out)
    if not failures:
        return []
    total = labelled + len(failures)
    lines = [f"{len(failures)} of {counted(total, 'pair')} failed to label: see {Path(out) / FAILURES_FILE} "
             "(a re-run of the job retries them)"]
    lines += [f"  {f['frame_id']}: {f.get('error', '?')}" for f in failures[:limit]]
    if len(failures) > limit:
        lines.append(f"  ... and {len(failures) - limit} more")
    return lines
