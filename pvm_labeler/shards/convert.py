"""Rewriting a shard directory: another compression (for tools without the Blosc plugin), or transformed labels."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from pvm_labeler.common.atomic import atomic_write_bytes
from pvm_labeler.common.errors import ShardError
from pvm_labeler.shards.reader import open_shard, read_index, read_sample, shard_sample_ids
from pvm_labeler.shards.schema import (
    DEFAULT_COMPRESSION,
    INDEX_NAME,
    OPTIONAL,
    REQUIRED,
    ShardRecord,
    ShardSample,
)
from pvm_labeler.shards.writer import ShardWriter, write_index

#: A sample -> the arrays (by schema name) and attributes to replace in its copy.
Transform = Callable[[ShardSample], tuple[dict[str, np.ndarray], dict[str, Any]]]


def convert(src: Path | str, out: Path | str, compression: str = "lzf", progress: bool = False) -> Path:
    """Rewrite a shard directory with another compression (e.g. lzf for tools without the Blosc plugin).

    Every sample is copied array by array with its attributes; shard names, order and the labeler config stay, so
    the trainer and ``verify`` treat the copy like the original.

    Returns:
        The output directory.
    """
    return rewrite(src, out, compression, extra={"converted_from": str(src), "compression": compression},
                   progress=progress)


#: Written into OUT while a rewrite runs: its source and settings, so that a re-run resumes only the same rewrite.
MARKER = ".rewrite.json"


def rewrite(src: Path | str, out: Path | str, compression: str = DEFAULT_COMPRESSION,
            transform: Transform | None = None, extra: dict[str, Any] | None = None, progress: bool = False) -> Path:
    """Copy a shard directory sample by sample, each through ``transform`` (None: unchanged), into ``out``.

    Each shard is written as ``.tmp`` and renamed, and ``index.json`` (with ``extra`` added) is written last: an
    interrupted rewrite never looks complete. A re-run with the same source and settings (``extra``, compression)
    resumes: it keeps the finished shards that read back with the right sample ids and writes the rest.
    ``progress``: a tqdm bar over the samples on stderr (when it is a terminal).
    """
    import sys

    from tqdm import tqdm

    src, out = Path(src), Path(out)
    extra = {k: str(Path(v).resolve()) if k in SOURCE_KEYS else v for k, v in (extra or {}).items()}  # any cwd
    if src.resolve() == out.resolve():
        raise ShardError(f"rewrite: the output {out} must differ from the input {src}")
    index = read_index(src)
    _require_own_out(out, src)
    out.mkdir(parents=True, exist_ok=True)
    resuming = _claim(out, {"src": str(src.resolve()), "compression": compression, "extra": extra or {}})
    # An index left by an earlier complete rewrite into OUT must not make this unfinished one look complete.
    (out / INDEX_NAME).unlink(missing_ok=True)
    if not resuming:  # shards of an earlier rewrite with other settings must not pass for this one's
        for stale in out.glob("*.h5"):
            stale.unlink()
    bar = tqdm(total=index.num_samples, unit="pair", desc=f"rewrite {src.name}", file=sys.stderr,
               disable=not (progress and sys.stderr.isatty()), dynamic_ncols=True)
    for path, ids in index.shards:
        if not (resuming and _finished(out / path.name, ids)):
            _rewrite_shard(path, ids, out / path.name, index.config, compression, transform)
        bar.update(len(ids))
    bar.close()
    kept = {k: v for k, v in index.raw.items() if k not in ("schema", "config", "code_version", "git_commit",
                                                             "dataset", "created", "shards", "num_samples")}
    write_index(out, [(path.name, ids) for path, ids in index.shards], index.config, index.dataset,
                {**kept, **(extra or {})})
    (out / MARKER).unlink()
    return out


#: The index keys in which each rewrite records its source (convert, densify, optstereo-distill fill).
SOURCE_KEYS = ("converted_from", "densified_from", "distilled_from")


def _require_own_out(out: Path, src: Path) -> None:
    """ShardError unless ``out`` is new, empty, an interrupted rewrite (its marker) or an earlier rewrite of ``src``:
    shards of another job (a labeling run's) were replaced in part and the rest left unindexed."""
    if not out.is_dir() or (out / MARKER).exists() or (not any(out.glob("*.h5")) and not (out / INDEX_NAME).exists()):
        return
    try:
        raw = json.loads((out / INDEX_NAME).read_text())
        sources = [Path(str(raw[key])) for key in SOURCE_KEYS if key in raw]
    except (OSError, ValueError):
        sources = []
    if not any(source.resolve() == src.resolve() for source in sources):
        raise ShardError(f"{out} holds shards that are no rewrite of {src} (another job's, e.g. a labeling run's): "
                         "give another output folder, or delete it first")


def _claim(out: Path, settings: dict[str, Any]) -> bool:
    """Mark ``out`` as being rewritten with ``settings``; True when an interrupted rewrite with the same settings
    left shards to keep (a marker with other settings, or none, starts over)."""
    marker = out / MARKER
    text = json.dumps(settings, sort_keys=True, default=str)
    same = marker.exists() and marker.read_text() == text
    atomic_write_bytes(marker, text.encode())
    return same


def _finished(path: Path, ids: list[str]) -> bool:
    """A shard file from an interrupted run that opens and lists exactly ``ids`` (a .tmp file never counts)."""
    if not path.exists():
        return False
    try:
        with open_shard(path) as h5:
            return shard_sample_ids(h5) == list(ids)
    except (ShardError, OSError, ValueError):
        return False


def _rewrite_shard(path: Path, ids: list[str], out_path: Path, config: dict[str, Any], compression: str,
                   transform: Transform | None) -> None:
    with open_shard(path) as h5, ShardWriter(out_path, config, compression=compression) as writer:
        for frame_id in ids:
            sample = read_sample(h5, frame_id)
            fields = {name: getattr(sample, name) for name in (*REQUIRED, *OPTIONAL)}
            attrs = dict(sample.attrs)
            if transform is not None:
                arrays, new_attrs = transform(sample)
                fields.update(arrays)
                attrs.update(new_attrs)
            writer.add(ShardRecord(frame_id=frame_id, attrs=attrs, **fields))
