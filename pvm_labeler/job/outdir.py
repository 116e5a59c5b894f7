"""The job's output directory: its identity (job.json), the files it owns, and which shards are already complete.

Existing shards are reused only when they come from the same job (config, dataset, shard size, compression);
``--overwrite`` deletes exactly the files in :data:`OWNED_GLOBS`, nothing else.
"""

from __future__ import annotations

import json
import logging
import tempfile
from pathlib import Path
from typing import Any

import yaml

from pvm_labeler.common.atomic import FAILURES_FILE, atomic_write_text, remove_outputs
from pvm_labeler.common.datasets import PairRef
from pvm_labeler.common.errors import InputError, ShardError, counted
from pvm_labeler.config import LabelerConfig
from pvm_labeler.job.spec import JobSpec
from pvm_labeler.job.worker import ShardOutcome
from pvm_labeler.shards import INDEX_NAME, TMP_SUFFIX, open_shard, shard_sample_ids, verify_shard

logger = logging.getLogger(__name__)

JOB_FILE = "job.json"
CONFIG_FILE = "config.yaml"
#: Files the job owns in its output directory (``overwrite`` deletes exactly these, nothing else).
OWNED_GLOBS: tuple[str, ...] = ("shard-*.h5", f"shard-*.h5{TMP_SUFFIX}", INDEX_NAME, JOB_FILE, CONFIG_FILE,
                                FAILURES_FILE) + tuple(f"{name}.*.tmp" for name in (INDEX_NAME, JOB_FILE, CONFIG_FILE,
                                                                                    FAILURES_FILE))
#: ``pvm-label report DIR``'s default folder (DIR/report): its files describe the labels of the run they read, so
#: ``--overwrite`` deletes them too (a stale report.md must not describe the new run's labels).
REPORT_GLOBS: tuple[str, ...] = ("report/report.md", "report/report.json", "report/density_vs_error.png",
                                 "report/run[0-9][0-9]-*/*.png")


def check_writable(out: Path) -> None:
    """Raise InputError naming ``--out`` when neither it nor its nearest existing parent takes a new file."""
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


def plan_shards(refs: list[PairRef], shard_size: int) -> list[list[PairRef]]:
    """The pairs of each shard, in frame-id order, ``shard_size`` per shard."""
    return [refs[i : i + shard_size] for i in range(0, len(refs), shard_size)]


def job_doc(spec: JobSpec, plan: list[list[PairRef]]) -> dict[str, Any]:
    """The content of ``job.json``: config, dataset, shard size, compression and the plan's frame ids."""
    return {
        "config": json.loads(spec.config.to_json()),
        "dataset": spec.dataset_info(),
        "shard_size": spec.shard_size,
        "compression": spec.compression,
        "plan": [[ref.frame_id for ref in shard] for shard in plan],
    }


def _identity(doc: dict[str, Any]) -> dict[str, Any]:
    """What must match for existing shards to be reusable: config, dataset, shard size, compression.

    The plan and --limit may change (e.g. a quick --limit 4 run, then the whole dataset): every shard is
    re-checked against its own planned frame ids, so shards whose frames did not change are kept.
    """
    identity = {k: v for k, v in doc.items() if k != "plan"}
    identity["dataset"] = {k: v for k, v in doc.get("dataset", {}).items() if k != "limit"}
    if isinstance(doc.get("config"), dict):
        # A field added since (e.g. c2_scale) takes its default, which reproduces the older labels exactly.
        identity["config"] = {**LabelerConfig().to_dict(), **doc["config"]}
    return identity


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


def _delete_default_report(out: Path) -> None:
    """Delete the files ``pvm-label report`` wrote into ``out/report`` and the folders that held only them."""
    if files := remove_outputs(out, REPORT_GLOBS):
        logger.info("--overwrite: deleted the earlier run's report (%d files in %s)", len(files), out / "report")


def _check_same_job(out: Path, doc: dict[str, Any]) -> None:
    """Raise InputError unless ``out/job.json`` describes the same job as ``doc`` (see :func:`_identity`)."""
    job_path = out / JOB_FILE
    if not job_path.is_file():
        raise InputError(f"--out {out} already holds shards from an unknown run (no {JOB_FILE}); "
                         f"pass --overwrite to replace them or choose another --out")
    try:
        old = json.loads(job_path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"cannot read {job_path}: {exc}; pass --overwrite to start afresh") from exc
    changes = _diff(_identity(old), _identity(doc))
    if changes:
        # Shards of an older default compression are still good: say how to keep them.
        same_but_compression = _identity({**old, "compression": doc["compression"]}) == _identity(doc)
        keep = f", or --compression {old['compression']} to continue them" if same_but_compression else ""
        raise InputError(f"existing shards in {out} were made with a different config/dataset ("
                         + "; ".join(changes[:6]) + f"); pass --overwrite to replace them{keep}, "
                         "or choose another --out")


def prepare_out(spec: JobSpec, doc: dict[str, Any]) -> None:
    """Check ``spec.out``, delete or vet a previous run's files, then write job.json and config.yaml."""
    out = spec.out
    check_writable(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} is a file, expected a directory")
    owned = _owned_files(out) if out.is_dir() else []
    if owned and spec.overwrite:
        logger.info("--overwrite: deleting %d files of a previous run in %s", len(owned), out)
        for path in owned:
            path.unlink()
        _delete_default_report(out)
    elif any(path.name.startswith("shard-") for path in owned):
        _check_same_job(out, doc)
    # else: an earlier run wrote its plan but no shard (it stopped before labelling, e.g. at an unreachable
    # --scheduler): nothing to keep, its job.json and config.yaml are replaced below
    out.mkdir(parents=True, exist_ok=True)
    # Shards past the end of the plan (an earlier run with a larger --limit) would linger unindexed: remove them,
    # saying so (they went silently, under a "nothing to do").
    beyond = [path for path in sorted(out.glob("shard-*.h5")) if (stem := path.name[len("shard-"): -len(".h5")])
              .isdigit() and int(stem) >= len(doc["plan"])]
    if beyond:
        logger.warning("removing %d labelled shard(s) of %s beyond this run's %d (an earlier run labelled more "
                       "pairs, e.g. with a larger --limit): %s", len(beyond), out, len(doc["plan"]),
                       ", ".join(path.name for path in beyond[:5]) + (" ..." if len(beyond) > 5 else ""))
    for path in beyond:
        path.unlink()
    atomic_write_text(out / JOB_FILE, json.dumps(doc, indent=2))
    atomic_write_text(out / CONFIG_FILE, yaml.safe_dump(spec.resolved(), sort_keys=False))


def complete_shard(path: Path, refs: list[PairRef], config: dict[str, Any]) -> ShardOutcome | None:
    """The outcome of an already complete shard (same plan and config, the same image files, every array
    readable), else None. Shards written before files were recorded (no ``source_digests`` attr) are not checked for
    changed images."""
    if not path.is_file():
        return None
    planned = [ref.frame_id for ref in refs]
    try:
        with open_shard(path) as h5:
            ids = shard_sample_ids(h5)
            old_planned = json.loads(h5.attrs["planned"])
            stats = json.loads(h5.attrs["stats"])
            sources = json.loads(h5.attrs["source_digests"]) if "source_digests" in h5.attrs else None
    except (ShardError, KeyError, ValueError, OSError) as exc:
        logger.warning("shard %s is not reusable (%s); relabelling it", path, exc)
        return None
    if old_planned != planned:
        logger.warning("shard %s holds another plan; relabelling it", path)
        return None
    changed = [ref.frame_id for ref in refs if sources is not None and sources.get(ref.frame_id)
               != ref.source_digest()]
    if changed:
        logger.warning("shard %s: the files of %s changed since it was labelled (%s); relabelling it", path,
                       counted(len(changed), "pair"), ", ".join(changed[:5]))
        return None
    problems = verify_shard(path, ids, config)
    if problems:
        logger.warning("shard %s is broken (%s); relabelling it", path, problems[0])
        return None
    return ShardOutcome(index=-1, file=path.name, sample_ids=ids, planned=planned, failures=stats["failures"],
                        stats=stats, seconds=0.0, peak_rss_mb=0.0, pid=0, resumed=True)
