"""The versioned HDF5 shard schema: THE contract between the labeler (writer) and the trainer (reader).

Layout of a shard directory ``DIR``::

    DIR/index.json        schema name + version, labeler config, code version + git commit, dataset info,
                          shards [{file, samples, count}], num_samples (written last, atomically)
    DIR/shard-00000.h5    one group per sample, named by its frame id:
        left, right           (H, W, 3) uint8 RGB
        label, label_right    (H, W) float32, NaN = no label (right view: right(x) matches left(x + d))
        confidence            (H, W) float16 in [0, 1], 0 where no label
        gt, gt_noc, gt_right  (H, W) float32, NaN = unknown -- only when the dataset has them
        confidence_right      (H, W) float16, the right view's -- optional (densify --views both writes it)
        attrs: sources (JSON), eps (K,), factors (K,), seed, plus free extras (timings JSON ...)
      root attrs: schema_name, schema_version, config (JSON), git_commit, code_version, samples (JSON list)

Frames of one dataset may differ in size, so every sample has its own shapes. Every array is chunked and
compressed: Blosc-LZ4 with byte shuffle by default (the HDF5 filter comes from ``hdf5plugin``, imported here so
every reader of this module can decode it; see docs/labeling.md for the measured size / speed of each option).

Writing: exactly one process writes a given shard, to ``shard-XXXXX.h5.tmp``, and :meth:`ShardWriter.close`
renames it with ``os.replace`` only when complete, so a half-written shard never looks complete. ``index.json`` is
written atomically the same way. Reading (no torch here): :func:`read_index`, :func:`open_shard`,
:func:`read_sample`, :func:`verify`.

Modules: ``schema`` (constants, records), ``writer``, ``reader``, ``verify``, ``convert``. The trainer imports this
package (never numba or the kernels), so it holds nothing but the format.

Making a tiny shard directory in tests (no labeler needed)::

    from pvm_labeler.shards import ShardRecord, write_shard_dir
    rec = ShardRecord(frame_id="a", left=l, right=r, label=lab, label_right=lab_r, confidence=conf, gt=gt)
    write_shard_dir(tmp_path / "shards", [rec, ...], config={"k": 2}, shard_size=2)
"""

from pvm_labeler.shards.convert import convert, rewrite
from pvm_labeler.shards.reader import open_shard, read_index, read_sample, shard_sample_ids
from pvm_labeler.shards.schema import (
    BLOSC_HINT,
    COMPRESSIONS,
    DEFAULT_COMPRESSION,
    INDEX_NAME,
    OPTIONAL,
    REQUIRED,
    SCHEMA_NAME,
    SCHEMA_VERSION,
    SHARD_PATTERN,
    TMP_SUFFIX,
    ShardIndex,
    ShardRecord,
    ShardSample,
    hdf5plugin,
    shard_name,
)
from pvm_labeler.shards.verify import header_problems, verify, verify_shard
from pvm_labeler.shards.writer import ShardWriter, write_index, write_shard_dir

__all__ = ["BLOSC_HINT", "COMPRESSIONS", "DEFAULT_COMPRESSION", "INDEX_NAME", "OPTIONAL", "REQUIRED", "SCHEMA_NAME",
           "SCHEMA_VERSION", "SHARD_PATTERN", "TMP_SUFFIX", "ShardIndex", "ShardRecord", "ShardSample", "ShardWriter",
           "convert", "hdf5plugin", "open_shard", "read_index", "read_sample", "rewrite", "shard_name",
           "shard_sample_ids", "header_problems", "verify", "verify_shard", "write_index", "write_shard_dir"]
