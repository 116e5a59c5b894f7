"""Writing shards: one process per file, ``shard-XXXXX.h5.tmp`` renamed on completion; index.json written last.

HDF5 builds the shard in memory and Python writes the finished image to disk. HDF5 reports a failed write (full
disk, file-size limit) only from object destructors ("Exception ignored in ObjectID.__dealloc__") and then may crash
the process in ``close``; Python's own ``write`` raises. So the disk is touched by one ``write`` + ``fsync`` per shard,
checked before (room for the shard) and after (the bytes on disk are the image), then renamed.
"""

from __future__ import annotations

import errno
import json
import os
import time
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from pvm_labeler.common.diskspace import NO_ROOM, disk_name, mb, require_room
from pvm_labeler.common.errors import DiskFullError, ShardError
from pvm_labeler.common.io import atomic_write_bytes
from pvm_labeler.common.version import code_version, git_commit
from pvm_labeler.shards import schema
from pvm_labeler.shards.schema import DEFAULT_COMPRESSION, ShardRecord, blosc_plugin, jsonable, shard_name


def _chunks(shape: tuple[int, ...]) -> tuple[int, ...]:
    # Row bands of full width: trainers read whole frames or random crops; 64-row bands keep a crop read to a few
    # chunks while a chunk (64 x 1242 x 3 = 238 kB) stays big enough for the compressor to do well.
    return (min(shape[0], 64), *shape[1:])


def _compression_kwargs(compression: str) -> Mapping[str, Any]:
    # Measured on KITTI frames (docs/labeling.md, `make bench`): Blosc-LZ4 + byte shuffle is as small as lzf and
    # writes ~4x / reads ~3x faster (it was ~15 % of a frame's labeling CPU with lzf); Blosc-Zstd level 1 + shuffle
    # is as small as gzip level 1 at about a third of its write time. The byte-shuffle filter gains nothing with lzf
    # (5.28 vs 5.29 MB/frame) but slows reads by ~25 %; for gzip it helps, and level 1 is within 2 % of level 4's
    # size at ~30 % less write time.
    hdf5plugin = blosc_plugin()
    if compression.startswith("blosc") and hdf5plugin is None:
        raise ShardError(f"--compression {compression} needs the hdf5plugin package; install it or use lzf")
    if compression == "blosc-lz4":
        return hdf5plugin.Blosc(cname="lz4", clevel=5, shuffle=hdf5plugin.Blosc.SHUFFLE)
    if compression == "blosc-zstd":
        return hdf5plugin.Blosc(cname="zstd", clevel=1, shuffle=hdf5plugin.Blosc.SHUFFLE)
    if compression == "lzf":
        return {"compression": "lzf"}
    if compression == "gzip":
        return {"compression": "gzip", "compression_opts": 1, "shuffle": True}
    if compression == "none":
        return {}
    raise ShardError(f"unknown compression '{compression}', expected one of {schema.COMPRESSIONS}")


class ShardWriter:
    """Writes one shard file: ``path.tmp`` while open, renamed to ``path`` by :meth:`close` when complete.

    Use as a context manager; on an exception the temporary file is deleted and nothing is renamed.

    Args:
        path: final shard path (``DIR/shard-00000.h5``).
        config: labeler config dict (stored as JSON in the root attrs, compared on resume).
        compression: one of COMPRESSIONS, "blosc-lz4" by default.
        extra_attrs: more root attributes (JSON-able values are stored as JSON strings).
        expected_bytes: the shard's expected size on disk (:func:`expected_shard_bytes`); when given, a disk without
            room for it raises :class:`DiskFullError` here, before any work goes into the shard.
    """

    def __init__(
        self,
        path: Path | str,
        config: dict[str, Any],
        compression: str = DEFAULT_COMPRESSION,
        extra_attrs: dict[str, Any] | None = None,
        expected_bytes: int | None = None,
    ) -> None:
        self.path = Path(path)
        self.tmp_path = self.path.with_name(self.path.name + schema.TMP_SUFFIX)
        self._kwargs = _compression_kwargs(compression)
        self._ids: list[str] = []
        if expected_bytes is not None:
            require_room(self.path, expected_bytes, "shard")
        # HDF5's core driver: the file lives in memory (backing_store=False) until close() writes its image
        self._file = h5py.File(self.tmp_path, "w", driver="core", backing_store=False)
        attrs = self._file.attrs
        attrs["schema_name"] = schema.SCHEMA_NAME
        attrs["schema_version"] = schema.SCHEMA_VERSION
        attrs["config"] = json.dumps(config, sort_keys=True, default=jsonable)
        attrs["git_commit"] = git_commit()
        attrs["code_version"] = code_version()
        attrs["compression"] = compression
        for key, value in (extra_attrs or {}).items():
            attrs[key] = value if isinstance(value, (str, int, float)) else json.dumps(value, default=jsonable)

    @property
    def sample_ids(self) -> list[str]:
        """Ids written so far, in order."""
        return list(self._ids)

    def add(self, record: ShardRecord) -> None:
        """Write one sample group (validates shapes and dtypes first)."""
        if record.frame_id in self._ids:
            raise ShardError(f"{self.tmp_path}: duplicate frame id '{record.frame_id}'")
        arrays = _record_arrays(record)
        group = self._file.create_group(record.frame_id)
        for name, array in arrays.items():
            # fletcher32: a chunk damaged on disk fails to read (verify, resume) instead of reading as other values
            group.create_dataset(name, data=array, chunks=_chunks(array.shape), fletcher32=True, **self._kwargs)
        for key, value in record.attrs.items():
            if isinstance(value, np.ndarray):
                group.attrs[key] = value
            elif isinstance(value, (int, float, str, np.integer, np.floating)):
                group.attrs[key] = value
            else:
                group.attrs[key] = json.dumps(value, sort_keys=True, default=jsonable)
        self._ids.append(record.frame_id)

    def set_attr(self, key: str, value: str | int | float) -> None:
        """Set a root attribute of the shard (e.g. summary statistics) before :meth:`close`."""
        self._file.attrs[key] = value

    def close(self) -> Path:
        """Finish the file and atomically publish it under its final name; returns the final path.

        Raises:
            DiskFullError: the disk (or the file-size limit) has no room for the shard; nothing is published and
                the temporary file is removed.
            ShardError: the bytes read back from disk are not the shard's.
        """
        self._file.attrs["samples"] = json.dumps(self._ids)
        self._file.attrs["num_samples"] = len(self._ids)
        self._file.flush()
        data = memoryview(self._file.id.get_file_image())
        self._file.close()
        try:
            require_room(self.path, len(data), "shard")
            _write_durably(self.tmp_path, data)
            os.replace(self.tmp_path, self.path)
            _fsync_directory(self.path.parent)
        except OSError as exc:
            self.tmp_path.unlink(missing_ok=True)
            if exc.errno in NO_ROOM:
                raise DiskFullError(f"disk full while writing shard {self.path} ({mb(len(data))}) on "
                                    f"{disk_name(self.path)}: {exc.strerror}; free space and re-run with --resume"
                                    ) from exc
            raise ShardError(f"cannot write shard {self.path}: {exc}") from exc
        except BaseException:
            self.tmp_path.unlink(missing_ok=True)
            raise
        return self.path

    def abort(self) -> None:
        """Close and drop the shard (nothing half-written is left behind)."""
        try:
            self._file.close()
        finally:
            self.tmp_path.unlink(missing_ok=True)

    def __enter__(self) -> ShardWriter:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def _write_durably(path: Path, data: memoryview) -> None:
    """Write ``data`` to ``path``, fsync it and check that the file on disk holds exactly ``len(data)`` bytes."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
    try:
        written = 0
        while written < len(data):
            n = os.write(fd, data[written:])
            if n == 0:  # a write that makes no progress: the disk takes nothing more
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
            written += n
        os.fsync(fd)
        size = os.fstat(fd).st_size
    finally:
        os.close(fd)
    if size != len(data):
        raise ShardError(f"shard {path}: {size} bytes on disk after writing {len(data)}")


def _fsync_directory(directory: Path) -> None:
    """Make a rename in ``directory`` durable (a crash after it must not bring back the old name)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:  # some file systems cannot open a directory: the rename is still atomic
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def expected_shard_bytes(pixels: int, with_gt: bool, compression: str) -> int:
    """A generous estimate of a shard's size on disk: ``pixels`` summed over its pairs.

    Per pixel: two RGB images (6 B), label, right label and confidence (12 B), GT maps (8 B); the compressors take
    that to about half (KITTI 2015 with GT, Blosc-LZ4: 12.6 B per pixel, 5.9 MB per frame, against 26 B raw), so
    0.7 of the raw size leaves a margin. ``none`` keeps the raw size.
    """
    raw = pixels * (6 + 12 + (8 if with_gt else 0))
    return int(raw if compression == "none" else 0.7 * raw)


def _record_arrays(record: ShardRecord) -> dict[str, np.ndarray]:
    fid = record.frame_id
    if not isinstance(fid, str) or not fid or "/" in fid or fid in (".", ".."):  # "/" made a nested HDF5 group
        raise ShardError(f"frame id {fid!r} cannot name a sample: a non-empty string without '/' (e.g. seq1-000); "
                         "pvm_labeler.common.datasets.safe_stem makes one")
    left = np.ascontiguousarray(record.left)
    if left.ndim != 3 or left.shape[2] != 3 or left.dtype != np.uint8:
        raise ShardError(f"sample {record.frame_id}: left must be (H, W, 3) uint8, got {left.shape} {left.dtype}")
    shape = left.shape[:2]
    arrays: dict[str, np.ndarray] = {"left": left}
    # every dataset the schema names (one list: an optional field added there is written without touching this)
    for name in (n for n in (*schema.REQUIRED, *schema.OPTIONAL) if n != "left"):
        value = getattr(record, name)
        if value is None:
            if name in schema.REQUIRED:
                raise ShardError(f"sample {record.frame_id}: '{name}' is required")
            continue
        dtype, ndim = (schema.REQUIRED | schema.OPTIONAL)[name]
        array = np.ascontiguousarray(value, dtype=dtype if name != "right" else None)
        if array.dtype != dtype or array.ndim != ndim or array.shape[:2] != shape:
            raise ShardError(
                f"sample {record.frame_id}: '{name}' must be {dtype} with {ndim} dims and size {shape}, "
                f"got {array.dtype} {array.shape}"
            )
        arrays[name] = array
    for name in ("confidence", "confidence_right"):  # the trainer's L_P weights: a value outside [0, 1] is a bug
        conf = arrays.get(name)
        if conf is not None and conf.size and not (np.nanmin(conf) >= 0 and np.nanmax(conf) <= 1):
            raise ShardError(f"sample {fid}: '{name}' must lie in [0, 1], got {np.nanmin(conf):g}..{np.nanmax(conf):g}")
    return arrays


def write_index(
    out_dir: Path | str,
    shards: Sequence[tuple[str, Sequence[str]]],
    config: dict[str, Any],
    dataset: dict[str, Any] | None = None,
    extra: dict[str, Any] | None = None,
) -> Path:
    """Write ``out_dir/index.json`` atomically.

    Args:
        out_dir: shard directory.
        shards: (shard file name relative to out_dir, sample ids) per shard, in order.
        config: labeler config dict.
        dataset: dataset info (name, root, split, ...).
        extra: further top-level entries (e.g. failures, timing summary).

    Returns:
        Path of the index file.
    """
    out_dir = Path(out_dir)
    doc: dict[str, Any] = {
        "schema": {"name": schema.SCHEMA_NAME, "version": schema.SCHEMA_VERSION},
        "config": config,
        "code_version": code_version(),
        "git_commit": git_commit(),
        "dataset": dataset or {},
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "shards": [{"file": name, "samples": list(ids), "count": len(ids)} for name, ids in shards],
        "num_samples": sum(len(ids) for _, ids in shards),
    }
    doc.update(extra or {})
    path = out_dir / schema.INDEX_NAME
    atomic_write_bytes(path, json.dumps(doc, indent=2, default=jsonable).encode())
    return path


def write_shard_dir(
    out_dir: Path | str,
    records: Iterable[ShardRecord],
    config: dict[str, Any] | None = None,
    dataset: dict[str, Any] | None = None,
    shard_size: int = 4,
    compression: str = DEFAULT_COMPRESSION,
) -> Path:
    """Test/demo helper: write records into ``shard-*.h5`` files of ``shard_size`` samples plus ``index.json``.

    Returns:
        The shard directory.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    config = dict(config or {})
    records = list(records)
    shards = []
    for index, start in enumerate(range(0, len(records), shard_size)):
        name = shard_name(index)
        with ShardWriter(out_dir / name, config, compression=compression) as writer:
            for record in records[start : start + shard_size]:
                writer.add(record)
        shards.append((name, writer.sample_ids))
    write_index(out_dir, shards, config, dataset)
    return out_dir
