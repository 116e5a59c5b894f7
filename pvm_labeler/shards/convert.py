"""Rewriting a shard directory: another compression (for tools without the Blosc plugin), or transformed labels."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from pvm_labeler.common.errors import ShardError
from pvm_labeler.shards.reader import open_shard, read_index, read_sample
from pvm_labeler.shards.schema import DEFAULT_COMPRESSION, OPTIONAL, REQUIRED, ShardRecord, ShardSample
from pvm_labeler.shards.writer import ShardWriter, write_index

#: A sample -> the arrays (by schema name) and attributes to replace in its copy.
Transform = Callable[[ShardSample], tuple[dict[str, np.ndarray], dict[str, Any]]]


def convert(src: Path | str, out: Path | str, compression: str = "lzf") -> Path:
    """Rewrite a shard directory with another compression (e.g. lzf for tools without the Blosc plugin).

    Every sample is copied array by array with its attributes; shard names, order and the labeler config stay, so
    the trainer and ``verify`` treat the copy like the original.

    Returns:
        The output directory.
    """
    return rewrite(src, out, compression, extra={"converted_from": str(src), "compression": compression})


def rewrite(src: Path | str, out: Path | str, compression: str = DEFAULT_COMPRESSION,
            transform: Transform | None = None, extra: dict[str, Any] | None = None) -> Path:
    """Copy a shard directory sample by sample, each through ``transform`` (None: unchanged), into ``out``.

    Each shard is written as ``.tmp`` and renamed, and ``index.json`` (with ``extra`` added) is written last: an
    interrupted rewrite never looks complete.
    """
    src, out = Path(src), Path(out)
    if src.resolve() == out.resolve():
        raise ShardError(f"rewrite: the output {out} must differ from the input {src}")
    index = read_index(src)
    out.mkdir(parents=True, exist_ok=True)
    names = []
    for path, ids in index.shards:
        with open_shard(path) as h5, ShardWriter(out / path.name, index.config, compression=compression) as writer:
            for frame_id in ids:
                sample = read_sample(h5, frame_id)
                fields = {name: getattr(sample, name) for name in (*REQUIRED, *OPTIONAL)}
                attrs = dict(sample.attrs)
                if transform is not None:
                    arrays, new_attrs = transform(sample)
                    fields.update(arrays)
                    attrs.update(new_attrs)
                writer.add(ShardRecord(frame_id=frame_id, attrs=attrs, **fields))
        names.append((path.name, ids))
    kept = {k: v for k, v in index.raw.items() if k not in ("schema", "config", "code_version", "git_commit",
                                                             "dataset", "created", "shards", "num_samples")}
    write_index(out, names, index.config, index.dataset, {**kept, **(extra or {})})
    return out
