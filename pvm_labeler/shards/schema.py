"""Schema constants and record types of the shard format (see :mod:`pvm_labeler.shards` for the layout)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

try:
    import hdf5plugin  # registers the Blosc filters with h5py: every shard reader imports this package
except ImportError:  # a machine without it still reads and writes lzf/gzip/none shards
    hdf5plugin = None

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
    "confidence_right": (np.dtype(np.float16), 2),
}
#: Datasets stored as float16 and read back as float32.
HALF_ON_DISK: tuple[str, ...] = ("confidence", "confidence_right")


def blosc_plugin() -> Any:
    """The ``hdf5plugin`` module, or None without it; read at call time (tests switch it off with
    ``monkeypatch.setattr(pvm_labeler.shards.schema, "hdf5plugin", None)``)."""
    return hdf5plugin


def shard_name(index: int) -> str:
    """File name of shard number ``index`` (``shard-00000.h5``)."""
    return SHARD_PATTERN.format(index=index)


def jsonable(value: Any) -> Any:
    """``json.dumps(default=...)`` hook: NumPy arrays and scalars, and paths."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON-serialisable: {type(value)}")


def decode_attr(value: Any) -> Any:
    """An HDF5 attribute as Python: bytes decoded, JSON strings parsed, NumPy scalars unwrapped."""
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


@dataclass
class ShardRecord:
    """One sample to write (the writer's input).

    Attributes:
        frame_id: group name (no "/").
        left, right: (H, W, 3) uint8.
        label, label_right: (H, W) float32, NaN = no label.
        confidence: (H, W) float in [0, 1] (stored as float16).
        gt, gt_noc, gt_right: optional (H, W) float32, NaN = unknown.
        confidence_right: optional (H, W) float in [0, 1], the right view's (stored as float16); absent, a reader
            weighs the right-view labels 1.
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
    confidence_right: npt.NDArray[np.floating] | None = None
    attrs: dict[str, Any] = field(default_factory=dict)


@dataclass
class ShardSample:
    """One sample as read back (the trainer's view). Confidences are float32; absent optional maps are None."""

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
    confidence_right: npt.NDArray[np.float32] | None = None


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
