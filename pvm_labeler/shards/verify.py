"""Checking shards: one file (schema, config, sample list, every array readable) or a whole directory."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pvm_labeler.common.errors import ShardError
from pvm_labeler.shards.reader import open_shard, read_index, read_sample, shard_sample_ids
from pvm_labeler.shards.schema import HALF_ON_DISK, INDEX_NAME, OPTIONAL, REQUIRED, TMP_SUFFIX, ShardSample, jsonable


def verify_shard(path: Path, expected_ids: Sequence[str] | None, config: dict[str, Any] | None) -> list[str]:
    """Problems of one shard file (empty list = ok): schema, config, sample list, every array readable."""
    problems: list[str] = []
    try:
        h5 = open_shard(path)
    except ShardError as exc:
        return [str(exc)]
    with h5:
        try:
            ids = shard_sample_ids(h5)
        except (KeyError, ValueError, OSError) as exc:
            return [f"shard {path}: no readable sample list in root attrs ({exc})"]
        problems += _header_checks(h5, path, ids, expected_ids, config)
        if sorted(ids) != sorted(h5.keys()):
            problems.append(f"shard {path}: groups {sorted(h5.keys())} differ from sample list {sorted(ids)}")
        for frame_id in ids:
            try:
                sample = read_sample(h5, frame_id)
            except ShardError as exc:
                problems.append(str(exc))
                continue
            problems += _check_sample(path, sample)
    return problems


def _header_checks(h5: Any, path: Path, ids: list[str], expected_ids: Sequence[str] | None,
                   config: dict[str, Any] | None) -> list[str]:
    """A shard's sample list ``ids`` against the index's ``expected_ids`` and its root ``config`` attribute against
    the index's ``config`` (None: not checked)."""
    problems = []
    if expected_ids is not None and list(expected_ids) != ids:
        problems.append(f"shard {path}: holds samples {ids}, index lists {list(expected_ids)}")
    if config is not None and json.loads(h5.attrs["config"]) != json.loads(json.dumps(config, default=jsonable)):
        problems.append(f"shard {path}: labeler config differs from the index config")
    return problems


def header_problems(shard_dir: Path | str) -> list[str]:
    """The cheap part of :func:`verify` (no array is read): shards whose labeler config or sample list differ from
    the index's. A trainer warns with them before its first step.

    Raises:
        ShardError: the index or a shard cannot be opened (naming the file: a truncated shard fails here, before
            training, not in a data-loader worker).
    """
    index = read_index(Path(shard_dir))
    problems = []
    for path, ids in index.shards:
        with open_shard(path) as h5:
            try:
                problems += _header_checks(h5, path, shard_sample_ids(h5), ids, index.config)
            except (KeyError, ValueError) as exc:
                problems.append(f"shard {path}: unreadable root attributes ({exc})")
    return problems


def _check_sample(path: Path, sample: ShardSample) -> list[str]:
    shape = sample.left.shape[:2]
    out = []
    for name, (dtype, ndim) in (REQUIRED | OPTIONAL).items():
        array = getattr(sample, name)
        if array is None:
            continue
        if name in HALF_ON_DISK:
            dtype = np.dtype(np.float32)  # converted on read
        if array.dtype != dtype or array.ndim != ndim or array.shape[:2] != shape:
            out.append(f"shard {path}: sample '{sample.frame_id}' array '{name}' is {array.dtype} {array.shape}, "
                       f"expected {dtype} with {ndim} dims and size {shape}")
    return out


def verify(shard_dir: Path | str) -> list[str]:
    """Check a whole shard directory: index schema, shard files, counts, config, readability of every array.

    Returns:
        Human-readable problems, each naming the broken file; an empty list means the directory is sound.
    """
    shard_dir = Path(shard_dir)
    try:
        index = read_index(shard_dir)
    except ShardError as exc:
        return [str(exc)]
    problems = []
    total = sum(len(ids) for _, ids in index.shards)
    if index.num_samples == 0 and total == 0:
        problems.append(f"{shard_dir / INDEX_NAME}: lists no samples (nothing to train on; every pair failed?)")
    if total != index.num_samples:
        problems.append(f"{shard_dir / INDEX_NAME}: num_samples {index.num_samples} != sum of shard counts {total}")
    for entry in index.raw.get("shards", []):
        if entry.get("count") != len(entry.get("samples", [])):
            problems.append(f"{shard_dir / INDEX_NAME}: shard {entry.get('file')} count {entry.get('count')} != "
                            f"{len(entry.get('samples', []))} listed samples")
    seen: dict[str, str] = {}
    for path, ids in index.shards:  # one frame in two shards: the trainer would draw it twice as often
        for fid in ids:
            if fid in seen and seen[fid] != path.name:
                problems.append(f"{shard_dir / INDEX_NAME}: frame '{fid}' is in {seen[fid]} and {path.name}")
            seen.setdefault(fid, path.name)
    for path, ids in index.shards:
        problems += verify_shard(path, ids, index.config)
    for stale in sorted(shard_dir.glob(f"*{TMP_SUFFIX}")):
        problems.append(f"stale temporary file {stale} (left by an interrupted run; delete it or re-run the job)")
    return problems
