"""The labeling job: dataset in, versioned HDF5 shards out; resumable, parallel (joblib or Dask).

``run(spec)`` does, in order:

1. validate the options and the labeler config (nothing is written before every check passed);
2. discover the pairs and pre-flight them from file headers (missing/unreadable files, left/right/GT size
   mismatches, images too small for K and max_disp): ALL problems are reported at once, naming the files;
3. check the output directory: writable; existing shards must come from the same job (config, dataset, shard
   plan) unless ``overwrite``; ``job.json`` (the plan) and ``config.yaml`` (the resolved config) are written;
4. label the shards that are not complete yet (a shard is complete when its final file exists, opens, has the
   same config and plan and every array reads back) or that hold pairs which failed before (they are retried),
   one task per shard, streaming results back;
5. write ``failures.json`` if single pairs failed, then ``index.json`` last (atomically).

Shards are assigned deterministically (sorted frame ids, ``shard_size`` per shard) and every frame's labels depend
only on (config, frame id, pixels), so labels are identical for any ``jobs`` and backend, and a run killed at any
point and restarted finishes only the missing shards with the same result.

Modules: ``spec`` (JobSpec, pre-flight), ``outdir`` (job.json, owned files, complete shards), ``worker``
(label_shard), ``progress`` (the bar), ``summary`` (JobSummary, index.json), ``runner`` (run).
"""

from pvm_labeler.job.outdir import CONFIG_FILE, FAILURES_FILE, JOB_FILE, OWNED_GLOBS
from pvm_labeler.job.runner import longest_first, run
from pvm_labeler.job.spec import DEFAULT_LABELER, JobSpec, absolute_paths, predicted_work, preflight
from pvm_labeler.job.summary import JobSummary
from pvm_labeler.job.worker import ShardOutcome, ShardTask, label_shard

__all__ = ["CONFIG_FILE", "DEFAULT_LABELER", "FAILURES_FILE", "JOB_FILE", "OWNED_GLOBS", "JobSpec", "JobSummary",
           "ShardOutcome", "ShardTask", "absolute_paths", "label_shard", "longest_first", "predicted_work",
           "preflight", "run"]
