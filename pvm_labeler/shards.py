"""The versioned HDF5 shard schema: THE contract between the labeler (writer) and the trainer (reader).

Layout of a shard directory ``DIR``::

    DIR/index.json        schema name + version, labeler config, code version + git commit, dataset info,
                          shards [{file, samples, count}], num_samples (written last, atomically)
    DIR/shard-00000.h5    one group per sample, named by its frame id:
        left, right           (H, W, 3) uint8 RGB
        label, label_right    (H, W) float32, NaN = no label (right view: right(x) matches left(x + d))
        confidence            (H, W) float16 in [0, 1], 0 where no label
        gt, gt_noc, gt_right  (H, W) float32, NaN = unknown -- only when the dataset has them
        attrs: sources (JSON), eps (K,), factors (K,), seed, plus free extras (timings JSON ...)
      root attrs: schema_name, schema_version, config (JSON), git_commit, code_version, samples (JSON list)

Frames of one dataset may differ in size, so every sample has its own shapes. Every array is chunked and
compressed: Blosc-LZ4 with byte shuffle by default (the HDF5 filter comes from ``hdf5plugin``, imported here so
every reader of this module can decode it; see docs/labeling.md for the measured size / speed of each option).

Writing: exactly one process writes a given shard, to ``shard-XXXXX.h5.tmp``, and :meth:`ShardWriter.close`
renames it with ``os.replace`` only when complete, so a half-written shard never looks complete. ``index.json`` is
written atomically the same way. Reading (no torch here): :func:`read_index`, :func:`open_shard`,
:func:`read_sample`, :func:`verify`.

Making a tiny shard directory in tests (no labeler needed)::

    from pvm_labeler.shards import ShardRecord, write_shard_dir
    rec = ShardRecord(frame_id="a", left=l, right=r, label=lab, label_right=lab_r, confidence=conf, gt=gt)
    write_shard_dir(tmp_path / "shards", [rec, ...], config={"k": 2}, shard_size=2)
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import numpy.typing as npt

from pvm_labeler.common.errors import ShardError
from pvm_labeler.common.io import atomic_write_bytes
from pvm_labeler.common.version import code_version, git_commit

try:
    import hdf5plugin  # registers the Blosc filters with h5py: every shard reader imports this module
except ImportError:  # a machine without it still reads and writes lzf/gzip/none shards
    hdf5plugin = None

logger = logging.getLogger(__name__)

BLOSC_HINT = (
    "the shard is compressed with Blosc, an HDF5 filter plugin: `pip install hdf5plugin` and `import hdf5plugin` "
    "before opening it (or set HDF5_PLUGIN_PATH to hdf5plugin.PLUGINS_PATH for non-Python tools), or rewrite the "
    "directory without the plugin: `pvm-label convert DIR OUT --compression lzf`"
)

SCHEMA_NAME = "pvstereo-pvm-shards"
SCHEMA_VERSION = 1
INDEX_NAME = "index.json"
SHARD_PATTERN = "shard-{index:05d}.h5"
TMP_SUFFIX = ".tmp"
COMPRESSIONS: tuple[str, ...] = ("blosc-lz4", "blosc-zstd", "lzf", "gzip", "none")
DEFAULT_COMPRESSION = "blosc-lz4"

#: Datasets every sample group must hold, with their dtype and number of dimensions.
REQUIRED: dict[str, tuple[np.dtype, int]] = {
    "left": (np.dtype(np.uint8), 3),
    "right": (np.dtype(np.uint8), 3),
    "label": (np.dtype(np.float32), 2),
    "label_right": (np.dtype(np.float32), 2),
    "confidence": (np.dtype(np.float16), 2),
}
OPTIONAL: dict[str, tuple[np.dtype, int]] = {
    "gt": (np.dtype(np.float32), 2),
    "gt_noc": (np.dtype(np.float32), 2),
    "gt_right": (np.dtype(np.float32), 2),
}


def shard_name(index: int) -> str:
    """File name of shard number ``index`` (``shard-00000.h5``)."""
    return SHARD_PATTERN.format(index=index)


# ------------------------------------------------------------------------------------------------------ records
@dataclass
class ShardRecord:
    """One sample to write (the writer's input).

    Attributes:
        frame_id: group name (no "/").
        left, right: (H, W, 3) uint8.
        label, label_right: (H, W) float32, NaN = no label.
        confidence: (H, W) float in [0, 1] (stored as float16).
        gt, gt_noc, gt_right: optional (H, W) float32, NaN = unknown.
        attrs: sources (dict), eps, factors (arrays), seed (int), and any JSON-able extras.
    """

    frame_id: str
    left: npt.NDArray[np.uint8]
    right: npt.NDArray[np.uint8]
    label: npt.NDArray[np.float32]
    label_right: npt.NDArray[np.float32]
    confidence: npt.NDArray[np.floating]
    gt: npt.NDArray[np.float32] | None = None
    gt_noc: npt.NDArray[np.float32] | None = None
    gt_right: npt.NDArray[np.float32] | None = None
    attrs: dict[str, Any] = field(default_factory=dict)


@dataclass
class ShardSample:
    """One sample as read back (the trainer's view). ``confidence`` is float32; absent GT maps are None."""

    frame_id: str
    left: npt.NDArray[np.uint8]
    right: npt.NDArray[np.uint8]
    label: npt.NDArray[np.float32]
    label_right: npt.NDArray[np.float32]
    confidence: npt.NDArray[np.float32]
    gt: npt.NDArray[np.float32] | None
    gt_noc: npt.NDArray[np.float32] | None
    gt_right: npt.NDArray[np.float32] | None
    attrs: dict[str, Any]


@dataclass
class ShardIndex:
    """Parsed ``index.json``.

    Attributes:
        root: the shard directory.
        shards: (absolute shard path, sample ids in file order) per shard.
        num_samples: total sample count.
        config: labeler config dict.
        dataset: dataset info dict (name, root, split, ...).
        raw: the whole JSON document.
    """

    root: Path
    shards: list[tuple[Path, list[str]]]
    num_samples: int
    config: dict[str, Any]
    dataset: dict[str, Any]
    raw: dict[str, Any]


# ------------------------------------------------------------------------------------------------------ writing
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
    raise ShardError(f"unknown compression '{compression}', expected one of {COMPRESSIONS}")


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON-serialisable: {type(value)}")


class ShardWriter:
    """Writes one shard file: ``path.tmp`` while open, renamed to ``path`` by :meth:`close` when complete.

    Use as a context manager; on an exception the temporary file is deleted and nothing is renamed.

    Args:
        path: final shard path (``DIR/shard-00000.h5``).
        config: labeler config dict (stored as JSON in the root attrs, compared on resume).
        compression: one of COMPRESSIONS, "blosc-lz4" by default.
        extra_attrs: more root attributes (JSON-able values are stored as JSON strings).
    """

    def __init__(
        self,
        path: Path | str,
        config: dict[str, Any],
        compression: str = DEFAULT_COMPRESSION,
        extra_attrs: dict[str, Any] | None = None,
    ) -> None:
        self.path = Path(path)
        self.tmp_path = self.path.with_name(self.path.name + TMP_SUFFIX)
        self._kwargs = _compression_kwargs(compression)
        self._ids: list[str] = []
        self._file = h5py.File(self.tmp_path, "w")
        attrs = self._file.attrs
        attrs["schema_name"] = SCHEMA_NAME
        attrs["schema_version"] = SCHEMA_VERSION
        attrs["config"] = json.dumps(config, sort_keys=True, default=_jsonable)
        attrs["git_commit"] = git_commit()
        attrs["code_version"] = code_version()
        attrs["compression"] = compression
        for key, value in (extra_attrs or {}).items():
            attrs[key] = value if isinstance(value, (str, int, float)) else json.dumps(value, default=_jsonable)

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
            group.create_dataset(name, data=array, chunks=_chunks(array.shape), **self._kwargs)
        for key, value in record.attrs.items():
            if isinstance(value, np.ndarray):
                group.attrs[key] = value
            elif isinstance(value, (int, float, str, np.integer, np.floating)):
                group.attrs[key] = value
            else:
                group.attrs[key] = json.dumps(value, sort_keys=True, default=_jsonable)
        self._ids.append(record.frame_id)

    def set_attr(self, key: str, value: str | int | float) -> None:
        """Set a root attribute of the shard (e.g. summary statistics) before :meth:`close`."""
        self._file.attrs[key] = value

    def close(self) -> Path:
        """Finish the file and atomically publish it under its final name; returns the final path."""
        self._file.attrs["samples"] = json.dumps(self._ids)
        self._file.attrs["num_samples"] = len(self._ids)
        self._file.close()
        os.replace(self.tmp_path, self.path)
        return self.path

    def abort(self) -> None:
        """Close and delete the temporary file (nothing half-written is left behind)."""
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


def _record_arrays(record: ShardRecord) -> dict[str, np.ndarray]:
    left = np.ascontiguousarray(record.left)
    if left.ndim != 3 or left.shape[2] != 3 or left.dtype != np.uint8:
        raise ShardError(f"sample {record.frame_id}: left must be (H, W, 3) uint8, got {left.shape} {left.dtype}")
    shape = left.shape[:2]
    arrays: dict[str, np.ndarray] = {"left": left}
    for name in ("right", "label", "label_right", "confidence", "gt", "gt_noc", "gt_right"):
        value = getattr(record, name)
        if value is None:
            if name in REQUIRED:
                raise ShardError(f"sample {record.frame_id}: '{name}' is required")
            continue
        dtype, ndim = (REQUIRED | OPTIONAL)[name]
        array = np.ascontiguousarray(value, dtype=dtype if name != "right" else None)
        if array.dtype != dtype or array.ndim != ndim or array.shape[:2] != shape:
            raise ShardError(
                f"sample {record.frame_id}: '{name}' must be {dtype} with {ndim} dims and size {shape}, "
                f"got {array.dtype} {array.shape}"
            )
        arrays[name] = array
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
        "schema": {"name": SCHEMA_NAME, "version": SCHEMA_VERSION},
        "config": config,
        "code_version": code_version(),
        "git_commit": git_commit(),
        "dataset": dataset or {},
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "shards": [{"file": name, "samples": list(ids), "count": len(ids)} for name, ids in shards],
        "num_samples": sum(len(ids) for _, ids in shards),
    }
    doc.update(extra or {})
    path = out_dir / INDEX_NAME
    atomic_write_bytes(path, json.dumps(doc, indent=2, default=_jsonable).encode())
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


# ------------------------------------------------------------------------------------------------------ reading
def read_index(shard_dir: Path | str) -> ShardIndex:
    """Parse and check ``shard_dir/index.json``.

    Raises:
        ShardError: naming the file, when the index is missing/unparsable, has another schema name or version,
            or lists a shard file that does not exist.
    """
    shard_dir = Path(shard_dir)
    path = shard_dir / INDEX_NAME
    if not path.is_file():
        raise ShardError(f"no shard index at {path} (the labeling job writes it last; did it finish?)")
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ShardError(f"cannot parse shard index {path}: {exc}") from exc
    schema = doc.get("schema", {}) if isinstance(doc, dict) else {}
    if schema.get("name") != SCHEMA_NAME:
        raise ShardError(f"{path}: schema name {schema.get('name')!r}, expected {SCHEMA_NAME!r}")
    if schema.get("version") != SCHEMA_VERSION:
        raise ShardError(f"{path}: schema version {schema.get('version')!r}, this code reads version {SCHEMA_VERSION}")
    shards = []
    for entry in doc.get("shards", []):
        shard_path = shard_dir / entry["file"]
        if not shard_path.is_file():
            raise ShardError(f"{path}: lists shard {shard_path}, which does not exist")
        shards.append((shard_path, list(entry["samples"])))
    return ShardIndex(
        root=shard_dir,
        shards=shards,
        num_samples=int(doc.get("num_samples", sum(len(ids) for _, ids in shards))),
        config=doc.get("config", {}),
        dataset=doc.get("dataset", {}),
        raw=doc,
    )


def open_shard(path: Path | str) -> h5py.File:
    """Open a shard read-only after checking its root schema attributes.

    Raises:
        ShardError: naming the file, when it is missing, not HDF5 / truncated, or of another schema or version.
    """
    path = Path(path)
    if not path.is_file():
        raise ShardError(f"shard file not found: {path}")
    try:
        h5 = h5py.File(path, "r")
    except OSError as exc:
        raise ShardError(f"corrupt or truncated shard {path}: {exc}") from exc
    try:
        name = _decode_attr(h5.attrs.get("schema_name"))
        version = _decode_attr(h5.attrs.get("schema_version"))
    except (OSError, KeyError) as exc:
        h5.close()
        raise ShardError(f"corrupt shard {path}: cannot read root attributes ({exc})") from exc
    if name != SCHEMA_NAME or version is None or int(version) != SCHEMA_VERSION:
        h5.close()
        raise ShardError(
            f"shard {path}: schema {name!r} version {version!r}, expected {SCHEMA_NAME!r} version {SCHEMA_VERSION}"
        )
    return h5


def shard_sample_ids(h5: h5py.File) -> list[str]:
    """Sample ids of an open shard in write order (from the root attrs)."""
    return list(json.loads(h5.attrs["samples"]))


def _decode_attr(value: Any) -> Any:
    if isinstance(value, bytes):
        value = value.decode()
    if isinstance(value, str) and value[:1] in "{[":
        try:
            return json.loads(value)
        except json.JSONDecodeError:
            return value
    if isinstance(value, np.generic):
        return value.item()
    return value


def read_sample(h5: h5py.File, frame_id: str) -> ShardSample:
    """Read one sample group fully into memory.

    Raises:
        ShardError: naming the shard file and frame, when the group or a required array is missing or unreadable.
    """
    if frame_id not in h5:
        raise ShardError(f"shard {h5.filename}: no sample '{frame_id}'")
    group = h5[frame_id]
    try:
        arrays = {name: group[name][()] for name in (*REQUIRED, *OPTIONAL) if name in group}
    except (OSError, KeyError) as exc:
        text = str(exc).lower()
        hint = f"; {BLOSC_HINT}" if hdf5plugin is None or "filter" in text or "plugin" in text else ""
        raise ShardError(f"shard {h5.filename}: sample '{frame_id}' is unreadable ({exc}){hint}") from exc
    missing = [name for name in REQUIRED if name not in arrays]
    if missing:
        raise ShardError(f"shard {h5.filename}: sample '{frame_id}' lacks {missing}")
    return ShardSample(
        frame_id=frame_id,
        left=arrays["left"],
        right=arrays["right"],
        label=arrays["label"],
        label_right=arrays["label_right"],
        confidence=arrays["confidence"].astype(np.float32),
        gt=arrays.get("gt"),
        gt_noc=arrays.get("gt_noc"),
        gt_right=arrays.get("gt_right"),
        attrs={key: _decode_attr(value) for key, value in group.attrs.items()},
    )


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
        if expected_ids is not None and list(expected_ids) != ids:
            problems.append(f"shard {path}: holds samples {ids}, index lists {list(expected_ids)}")
        if config is not None and json.loads(h5.attrs["config"]) != json.loads(json.dumps(config, default=_jsonable)):
            problems.append(f"shard {path}: labeler config differs from the index config")
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


def _check_sample(path: Path, sample: ShardSample) -> list[str]:
    shape = sample.left.shape[:2]
    out = []
    for name, (dtype, ndim) in (REQUIRED | OPTIONAL).items():
        array = getattr(sample, name)
        if array is None:
            continue
        if name == "confidence":
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
    if total != index.num_samples:
        problems.append(f"{shard_dir / INDEX_NAME}: num_samples {index.num_samples} != sum of shard counts {total}")
    for entry in index.raw.get("shards", []):
        if entry.get("count") != len(entry.get("samples", [])):
            problems.append(f"{shard_dir / INDEX_NAME}: shard {entry.get('file')} count {entry.get('count')} != "
                            f"{len(entry.get('samples', []))} listed samples")
    for path, ids in index.shards:
        problems += verify_shard(path, ids, index.config)
    for stale in sorted(shard_dir.glob(f"*{TMP_SUFFIX}")):
        problems.append(f"stale temporary file {stale} (left by an interrupted run; delete it or re-run the job)")
    return problems


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
