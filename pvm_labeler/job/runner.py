"""``run(spec)``: check, plan, skip the complete shards (not those holding failed pairs: they are retried), fan the
rest out longest first, summarise."""

from __future__ import annotations

import logging
import time

from pvm_labeler.common.datasets import discover, first_gt_problems
from pvm_labeler.common.errors import counted
from pvm_labeler.job.outdir import complete_shard, job_doc, plan_shards, prepare_out
from pvm_labeler.job.progress import PairProgress, progress_bar
from pvm_labeler.job.spec import JobSpec, absolute_paths, preflight
from pvm_labeler.job.summary import FAILURES_FILE, JobSummary, finish
from pvm_labeler.job.worker import ShardOutcome, ShardTask, label_shard
from pvm_labeler.packgt import PACK_GT_LABELER, require_gt
from pvm_labeler.parallel import numba_threads_per_worker, run_tasks
from pvm_labeler.shards import INDEX_NAME, TMP_SUFFIX, shard_name

logger = logging.getLogger(__name__)


def longest_first(tasks: list[ShardTask], work: dict[str, int]) -> list[ShardTask]:
    """Tasks in descending predicted work: the cheapest shards run last, so workers finish close together
    (longest-processing-time-first scheduling). Shard files and labels do not depend on the order."""
    return sorted(tasks, key=lambda task: sum(work[ref.frame_id] for ref in task.refs), reverse=True)


def run(spec: JobSpec) -> JobSummary:
    """Run the labeling job described by ``spec`` (see :mod:`pvm_labeler.job`).

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
    if spec.label_fn == PACK_GT_LABELER:
        require_gt(refs)
    work, unusable = preflight(refs, spec.config, matcher=spec.label_fn != PACK_GT_LABELER, skip=spec.skip_unusable)
    if unusable:
        logger.warning("--skip-unusable: leaving out %s (listed in %s): %s", counted(len(unusable), "unusable pair"),
                       spec.out / FAILURES_FILE, "; ".join(f"{u['frame_id']}: {u['error']}" for u in unusable[:3])
                       + (" ..." if len(unusable) > 3 else ""))
        refs = [ref for ref in refs if ref.frame_id in work]
    gt_warnings = first_gt_problems(refs)  # a wrong --gt-scale or byte order is every file's: one pair tells
    for warning in gt_warnings:
        logger.warning("GT looks wrong: %s", warning)
    plan = plan_shards(refs, spec.shard_size)
    doc = job_doc(spec, plan)
    prepare_out(spec, doc)
    config = doc["config"]
    outcomes: dict[int, ShardOutcome] = {}
    pending: list[ShardTask] = []
    threads = spec.numba_threads or numba_threads_per_worker(spec.jobs)
    for index, shard_refs in enumerate(plan):
        path = spec.out / shard_name(index)
        done = complete_shard(path, shard_refs, config) if spec.resume else None
        if done is not None and done.failures:
            # Pairs that failed before are retried (a fixed image gets its label): the shard is relabelled whole
            # into shard.tmp; the old file stays valid until the new one replaces it.
            logger.info("shard %s: retrying %s that failed before (%s)", path.name,
                        counted(len(done.failures), "pair"), ", ".join(f["frame_id"] for f in done.failures[:5]))
            done = None
        if done is not None:
            done.index = index
            outcomes[index] = done
        else:
            path.with_name(path.name + TMP_SUFFIX).unlink(missing_ok=True)  # stale from a killed run
            # Absolute paths: Dask workers may run in another working directory, or on another machine.
            pending.append(ShardTask(index, str(path.resolve()), [absolute_paths(r) for r in shard_refs], config,
                                     spec.compression, threads, spec.label_fn))
    pending = longest_first(pending, work)
    if pending:
        # An index next to a partial set of shards would look complete to a reader; it is rewritten at the end.
        (spec.out / INDEX_NAME).unlink(missing_ok=True)
    logger.info("%d pairs in %d shards: %d complete, %d to label (%s, %d jobs, %d numba threads each)",
                len(refs), len(plan), len(outcomes), len(pending), spec.backend, spec.jobs, threads)
    _label_pending(spec, pending, outcomes, len(refs), len(plan))
    return finish(spec, refs, plan, outcomes, threads, time.perf_counter() - t0, gt_warnings, unusable)


def _label_pending(spec: JobSpec, pending: list[ShardTask], outcomes: dict[int, ShardOutcome], pairs: int,
                   shards: int) -> None:
    """Run the pending shard tasks, adding each outcome to ``outcomes`` as it arrives (progress bar on stderr)."""
    bar = progress_bar(pairs, sum(len(o.planned) for o in outcomes.values()), spec.quiet)
    with PairProgress(bar, spec, pending) as per_pair:
        for outcome in run_tasks(label_shard, pending, spec.backend, spec.jobs, spec.scheduler):
            outcomes[outcome.index] = outcome
            if not per_pair.active:
                bar.update(len(outcome.planned))
            bar.set_postfix(shards=f"{len(outcomes)}/{shards}")
