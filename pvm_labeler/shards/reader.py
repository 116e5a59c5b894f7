"""Reading shards (no torch here): the index, one shard file, one sample; every error names the file."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from pvm_labeler.common.errors import ShardError
from pvm_labeler.shards.schema import (
    BLOSC_HINT,
    HALF_ON_DISK,
    INDEX_NAME,
    OPTIONAL,
    REQUIRED,
    SCHEMA_NAME,
    SCHEMA_VERSION,
    ShardIndex,
    ShardSample,
    blosc_plugin,
    decode_attr,
)


def read_index(shard_dir: Path | str) -> ShardIndex:
    """Parse and check ``shard_dir/index.json``.

    Raises:
        ShardError: naming the file, when the index is missing/unparsable, has another schema name or version,
            lists a shard file that does not exist, or one outside ``shard_dir`` (an absolute path or one through
            ``..``: the index is a file anyone can write, and its entries are names inside the folder).
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
        name = entry.get("file") if isinstance(entry, dict) else None
        if not isinstance(name, str) or not isinstance(entry.get("samples"), list):
            raise ShardError(f"{path}: a shard entry must hold 'file' (a name) and 'samples' (a list), got {entry!r}")
        if Path(name).is_absolute() or ".." in Path(name).parts or not Path(name).parts:
            raise ShardError(f"{path}: lists shard {name!r}, which is not a file inside {shard_dir}; its shard "
                             f"entries are file names in the index's own folder")
        shard_path = shard_dir / name
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
        name = decode_attr(h5.attrs.get("schema_name"))
        version = decode_attr(h5.attrs.get("schema_version"))
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
        arrays.update({name: arrays[name].astype(np.float32) for name in HALF_ON_DISK if name in arrays})
    except (OSError, KeyError) as exc:
        raise ShardError(f"shard {h5.filename}: sample '{frame_id}' is unreadable ({exc}){_read_hint(exc)}") from exc
    missing = [name for name in REQUIRED if name not in arrays]
    if missing:
        raise ShardError(f"shard {h5.filename}: sample '{frame_id}' lacks {missing}")
    size = arrays["left"].shape[:2]
    off = {name: a.shape[:2] for name, a in arrays.items() if a.shape[:2] != size}
    if off:  # a label of another size would be cropped against the wrong pixels, or fail deep in a transform
        raise ShardError(f"shard {h5.filename}: sample '{frame_id}' has arrays of other sizes than its left image "
                         f"{size}: {off}")
    return ShardSample(
        frame_id=frame_id,
        left=arrays["left"],
        right=arrays["right"],
        label=arrays["label"],
        label_right=arrays["label_right"],
        confidence=arrays["confidence"],
        gt=arrays.get("gt"),
        gt_noc=arrays.get("gt_noc"),
        gt_right=arrays.get("gt_right"),
        attrs={key: decode_attr(value) for key, value in group.attrs.items()},
        confidence_right=arrays.get("confidence_right"),
    )


def _read_hint(exc: Exception) -> str:
    """Why a sample's arrays failed to read: no Blosc plugin (its hint), or, with the plugin there, a damaged file
    (a checksum or decompression failure: it named the missing plugin)."""
    text = str(exc).lower()
    if blosc_plugin() is None or "not registered" in text or "plugin" in text or "can't open" in text:
        return f"; {BLOSC_HINT}"
    if "filter" in text or "checksum" in text:
        return ("; the file is damaged (its data fails its checksum or decompression): re-run the job that wrote it "
                "(a labeling run rewrites broken shards) or restore the file")
    return ""
