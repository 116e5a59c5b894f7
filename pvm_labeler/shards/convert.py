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


def convert(src: Path | str, out: Path | str, compression: str = "lzf", progress: bool = False) -> Path:
    """Rewrite a shard directory with another compression (e.g. lzf for tools without the Blosc plugin).

    Every sample is copied array by array with its attributes; shard names, order and the labeler config stay, so
    the trainer and ``verify`` treat the copy like the original.

    Returns:
        The output directory.
    """
    return rewrite(src, out, compression, extra={"converted_from": str(src), "compression": compression},
                   progress=progress)


def rewrite(src: Path | str, out: Path | str, compression: str = DEFAULT_COMPRESSION,
            transform: Transform | None = None, extra: dict[str, Any] | None = None, progress: bool = False) -> Path:
    """Copy a shard directory sample by sample, each through ``transform`` (None: unchanged), into ``out``.

    ``progress``: a tqdm bar over the samples on stderr (when it is a terminal).

    Each shard is written as ``.tmp`` and renamed, and ``index.json`` (with ``extra`` added) is written last: an
    interrupted rewrite never looks complete.
    """
    src, out = Path(src), Path(out)
    if src.resolve() == out.resolve():
        raise ShardError(f"rewrite: the output {out} must differ from the input {src}")
    import sys

    from tqdm import tqdm

    index = read_index(src)
    out.mkdir(parents=True, exist_ok=True)
    names = []
    bar = tqdm(total=index.num_samples, unit="pair", desc=f"rewrite {src.name}", file=sys.stderr,
               disable=not (progress and sys.stderr.isatty()), dynamic_ncols=True)
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
                bar.update()
        names.append((path.name, ids))
    bar.close()
    kept = {k: v for k, v in index.raw.items() if k not in ("schema", "config", "code_version", "git_commit",
                                                             "dataset", "created", "shards", "num_samples")}
    write_index(out, names, index.config, index.dataset, {**kept, **(extra or {})})
    return out
