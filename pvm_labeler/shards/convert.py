"""Rewriting a shard directory with another compression (for tools without the Blosc plugin)."""

from __future__ import annotations

from pathlib import Path

from pvm_labeler.common.errors import ShardError
from pvm_labeler.shards.reader import open_shard, read_index, read_sample
from pvm_labeler.shards.schema import OPTIONAL, REQUIRED, ShardRecord
from pvm_labeler.shards.writer import ShardWriter, write_index


def convert(src: Path | str, out: Path | str, compression: str = "lzf") -> Path:
    """Rewrite a shard directory with another compression (e.g. lzf for tools without the Blosc plugin).

    Every sample is copied array by array with its attributes; shard names, order and the labeler config stay, so
    the trainer and ``verify`` treat the copy like the original. Each shard is written as ``.tmp`` and renamed, and
    ``index.json`` is written last: an interrupted conversion never looks complete.

    Returns:
        The output directory.
    """
    src, out = Path(src), Path(out)
    if src.resolve() == out.resolve():
        raise ShardError(f"convert: the output {out} must differ from the input {src}")
    index = read_index(src)
    out.mkdir(parents=True, exist_ok=True)
    names = []
    for path, ids in index.shards:
        with open_shard(path) as h5, ShardWriter(out / path.name, index.config, compression=compression) as writer:
            for frame_id in ids:
                sample = read_sample(h5, frame_id)
                fields = {name: getattr(sample, name) for name in (*REQUIRED, *OPTIONAL)}
                writer.add(ShardRecord(frame_id=frame_id, attrs=sample.attrs, **fields))
        names.append((path.name, ids))
    extra = {k: v for k, v in index.raw.items() if k not in ("schema", "config", "code_version", "git_commit",
                                                              "dataset", "created", "shards", "num_samples")}
    write_index(out, names, index.config, index.dataset, {**extra, "converted_from": str(src),
                                                          "compression": compression})
    return out
