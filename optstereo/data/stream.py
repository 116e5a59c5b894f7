"""ShardStream: a torch IterableDataset over the labeler's HDF5 shards.

Reads only through the schema module ``pvm_labeler.shards`` (read_index / open_shard / read_sample), so a wrong
schema version, an empty directory or a corrupt shard fails with a ShardError naming the file.

Work split (TIMM ``reader_wds.py`` ``_split_by_node_and_worker``): with R ranks and N DataLoader workers per rank
there are R * N global workers; global worker ``g = rank * N + worker_id`` takes shards ``g, g + R*N, ...``. When
there are fewer shards than global workers the SAMPLES are split the same way instead (and when there are fewer
samples than global workers, worker g takes sample ``g mod n``), so every rank still gets data.

Order: each epoch, a worker visits its shards in a seeded random order and passes the frame ids through a seeded
shuffle buffer (seed, epoch, g). Shuffling ids rather than decoded samples keeps memory flat and makes skipping
the already-consumed part of the stream on ``--resume`` free. Augmentation randomness comes from a generator
seeded by (seed, epoch, g, sample counter), so a resumed stream continues exactly where the old one stopped.

h5py files are never opened in ``__init__``; each worker opens its shards lazily (h5py docs, "multiprocessing"),
keeping at most ``max_open`` handles.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import IterableDataset, get_worker_info

from optstereo.choices import SUPERVISIONS, Supervision
from optstereo.data.transforms import TrainTransform, to_tensors
from pvm_labeler.common.errors import ConfigError, ShardError
from pvm_labeler.shards import ShardIndex, open_shard, read_index, read_sample

logger = logging.getLogger(__name__)

SampleKey = tuple[str, str]  # (shard path, frame id)


def shuffle_buffer(items: list[SampleKey], size: int, rng: np.random.Generator) -> Iterator[SampleKey]:
    """Stream ``items`` through a shuffle buffer of ``size`` entries (webdataset-style reservoir)."""
    buffer: list[SampleKey] = []
    for item in items:
        if len(buffer) < size:
            buffer.append(item)
            continue
        k = int(rng.integers(len(buffer)))
        yield buffer[k]
        buffer[k] = item
    order = rng.permutation(len(buffer))
    for k in order:
        yield buffer[int(k)]


def skip_count(skip_batches: int, batch_size: int, worker_id: int, num_workers: int) -> int:
    """Samples worker ``worker_id`` produced in the first ``skip_batches`` batches.

    A DataLoader over an IterableDataset builds each batch from one worker and visits workers round-robin, so
    worker w made the batches j < skip_batches with j mod num_workers == w.
    """
    num_workers = max(num_workers, 1)
    batches = skip_batches // num_workers + (1 if worker_id < skip_batches % num_workers else 0)
    return batches * batch_size


def check_supervision(labels_dir: Path | str, supervision: str, index: ShardIndex | None = None) -> None:
    """ConfigError when ``supervision`` "pvm" meets a GT pack (``pvm-label pack-gt``: no PVM label; L_P would be 0
    and only the photometric terms would train). ``index``: the folder's, when already read."""
    index = index if index is not None else read_index(Path(labels_dir))
    # summary.gt_only, or (packs made before it was recorded) the pack's labeler config: labels none
    gt_pack = ((index.raw.get("summary") or {}).get("gt_only")
               or (index.config.get("extra") or {}).get("labels") == "none")
    if supervision == "pvm" and gt_pack:
        raise ConfigError(f"{labels_dir} is a GT pack (pvm-label pack-gt: images and GT, no PVM labels): train on it "
                          "with --supervision gt, or label its pairs with pvm-label run")


class ShardStream(IterableDataset):
    """Infinite (or one-epoch) stream of augmented training samples from a shard directory.

    Yields ``(left, right, label, valid)``: left/right (3, h, w) float32 in [0, 255], label (1, h, w) float32
    (0 where invalid), valid (1, h, w) bool; with ``with_ids=True`` the frame id (str) is appended.

    Args:
        labels_dir: directory with index.json and shard-*.h5.
        supervision: "pvm" reads ``label``/``label_right``; "gt" reads ``gt``/``gt_right``.
        transform: TrainTransform (crop, flip-swap, jitter); None = whole frames, no augmentation.
        seed: base seed of shuffling and augmentation.
        shuffle_size: shuffle buffer size in samples (1 = no shuffling within a worker).
        max_disp: labels >= max_disp are invalid.
        rank, world_size: DDP position; None = read from torch.distributed when initialised, else (0, 1).
        infinite: loop over epochs forever (training); False = one epoch.
        with_ids: append the frame id to every yielded tuple.
        with_confidence: also yield the PVM confidence (1, h, w) float32 after ``valid`` (weights of a
            confidence-weighted L_P; flip-swapped samples get the right view's, else 1).
        skip_batches, batch_size: skip what the first ``skip_batches`` batches consumed (resume); worker roles
            are rotated so batch ``skip_batches`` comes from the worker that would have made it.
    """

    def __init__(
        self,
        labels_dir: Path,
        *,
        supervision: Supervision = "pvm",
        transform: TrainTransform | None = None,
        seed: int = 0,
        shuffle_size: int = 16,
        max_disp: float = float("inf"),
        rank: int | None = None,
        world_size: int | None = None,
        infinite: bool = True,
        with_ids: bool = False,
        skip_batches: int = 0,
        batch_size: int = 1,
        max_open: int = 8,
        with_confidence: bool = False,
    ) -> None:
        super().__init__()
        if supervision not in SUPERVISIONS:
            raise ValueError(f"supervision must be one of {SUPERVISIONS}, got {supervision!r}")
        self.labels_dir = Path(labels_dir)
        index = read_index(self.labels_dir)  # JSON only; raises ShardError naming index.json
        self.shards: list[tuple[str, list[str]]] = [(str(p), [str(i) for i in ids]) for p, ids in index.shards]
        self.num_samples = sum(len(ids) for _, ids in self.shards)
        if self.num_samples == 0:
            raise ShardError(f"shard directory {self.labels_dir} holds no samples (index.json lists none)")
        check_supervision(self.labels_dir, supervision, index)
        self.supervision = supervision
        self.transform = transform
        self.seed = int(seed)
        self.shuffle_size = max(int(shuffle_size), 1)
        self.max_disp = float(max_disp)
        self._rank, self._world_size = rank, world_size
        self.infinite = infinite
        self.with_ids = with_ids
        self.with_confidence = with_confidence
        self.skip_batches = int(skip_batches)
        self.batch_size = int(batch_size)
        self.max_open = max_open
        self._handles: OrderedDict[str, Any] = OrderedDict()

    # -- work split ---------------------------------------------------------------------------------------------
    def _dist(self) -> tuple[int, int]:
        if self._rank is not None and self._world_size is not None:
            return self._rank, self._world_size
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            return torch.distributed.get_rank(), torch.distributed.get_world_size()
        return 0, 1

    def assignment(self, global_worker: int, num_global: int) -> tuple[str, list[SampleKey]]:
        """("shards" | "samples", this worker's (shard, frame id) keys in index order)."""
        if len(self.shards) >= num_global:
            mine = self.shards[global_worker::num_global]
            return "shards", [(path, fid) for path, ids in mine for fid in ids]
        keys = [(path, fid) for path, ids in self.shards for fid in ids]
        if len(keys) >= num_global:
            return "samples", keys[global_worker::num_global]
        return "samples", [keys[global_worker % len(keys)]]

    def balanced_block(self, epoch: int, global_worker: int, num_global: int) -> list[SampleKey]:
        """An infinite stream's share of ``epoch``: the shards in an order seeded by (seed, epoch) alone (the same in
        every worker), their samples laid end to end as a ring and cut, from a seeded start, into ``num_global``
        runs of ceil(total / num_global). Every worker yields as many samples (the DataLoader takes
        them in turn), so no sample comes round more often because its worker holds fewer: a 2+2+1-sample split
        over 2 workers gave 1.5x to two of five frames. The padding repeats fewer than ``num_global`` samples per
        epoch, other ones each epoch; a run reads whole shards in order, as before."""
        rng = np.random.default_rng([self.seed, epoch, 1])
        order = rng.permutation(len(self.shards))
        keys = [(self.shards[int(k)][0], fid) for k in order for fid in self.shards[int(k)][1]]
        if not keys:
            return []
        length = -(-len(keys) // num_global)
        start = int(rng.integers(len(keys))) + global_worker * length  # a seeded start: any sample may be repeated
        return [keys[i % len(keys)] for i in range(start, start + length)]

    def epoch_order(self, epoch: int, global_worker: int, num_global: int) -> list[SampleKey]:
        """The keys one global worker visits in ``epoch``: an infinite stream's balanced share
        (:meth:`balanced_block`), one epoch's its own shards (each sample once across workers) in a seeded shard
        order; then the shuffle buffer."""
        rng = np.random.default_rng([self.seed, epoch, global_worker, 0])
        if self.infinite:
            return list(shuffle_buffer(self.balanced_block(epoch, global_worker, num_global), self.shuffle_size, rng))
        mode, keys = self.assignment(global_worker, num_global)
        if mode == "shards":
            by_shard: dict[str, list[SampleKey]] = {}
            for key in keys:
                by_shard.setdefault(key[0], []).append(key)
            shard_order = [list(by_shard)[int(k)] for k in rng.permutation(len(by_shard))]
            keys = [key for shard in shard_order for key in by_shard[shard]]
        return list(shuffle_buffer(keys, self.shuffle_size, rng))

    # -- reading ------------------------------------------------------------------------------------------------
    def _open(self, path: str) -> Any:
        handle = self._handles.pop(path, None)
        if handle is None:
            handle = open_shard(Path(path))
            while len(self._handles) >= self.max_open:
                self._handles.popitem(last=False)[1].close()
        self._handles[path] = handle
        return handle

    def close(self) -> None:
        """Close every open shard handle of this process."""
        while self._handles:
            self._handles.popitem()[1].close()

    def count_unflippable(self) -> int:
        """Samples of this stream without a right-view label (``gt_right`` for "gt", ``label_right`` for "pvm"): the
        flip-swap can never apply to them. Reads group keys only (no arrays), closing the files again."""
        if self.supervision == "pvm":
            return 0  # label_right is a required array of the schema: every PVM sample can be flipped
        key = "gt_right"
        missing = 0
        for path, ids in self.shards:
            with open_shard(path) as h5:
                missing += sum(1 for frame_id in ids if frame_id not in h5 or key not in h5[frame_id])
        return missing

    def read(self, path: str, frame_id: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """(left, right, label, label_right or None) of one sample for the configured supervision."""
        return self._read(path, frame_id)[:4]

    def _read(self, path: str, frame_id: str) -> tuple:
        """read() plus the sample's confidence (1 where the supervision is GT) and the right view's (None when the
        shards hold none, or the supervision is GT)."""
        sample = read_sample(self._open(path), frame_id)
        if self.supervision == "gt":
            if sample.gt is None:
                raise ShardError(
                    f"--supervision gt needs ground truth, but sample {frame_id!r} in shard {path} has no 'gt' "
                    "(label a dataset with GT, or use --supervision pvm)"
                )
            return sample.left, sample.right, sample.gt, sample.gt_right, np.ones_like(sample.gt), None
        return (sample.left, sample.right, sample.label, sample.label_right, sample.confidence,
                sample.confidence_right)

    # -- iteration ----------------------------------------------------------------------------------------------
    def __iter__(self) -> Iterator[tuple]:
        info = get_worker_info()
        worker_id, num_workers = (0, 1) if info is None else (info.id, info.num_workers)
        # The DataLoader asks worker 0 for the first batch of every run, but after ``skip_batches`` batches the
        # uninterrupted run would ask worker (skip_batches mod N) next: rotate the roles so both runs agree.
        worker_id = (worker_id + self.skip_batches) % num_workers
        rank, world_size = self._dist()
        global_worker, num_global = rank * num_workers + worker_id, world_size * num_workers
        skip = skip_count(self.skip_batches, self.batch_size, worker_id, num_workers)
        counter, epoch = 0, 0
        try:
            while True:
                order = self.epoch_order(epoch, global_worker, num_global)
                if not order:
                    return
                for path, frame_id in order:
                    counter += 1
                    if counter <= skip:
                        continue
                    rng = np.random.default_rng([self.seed, epoch, global_worker, counter])
                    yield self._make(path, frame_id, rng)
                epoch += 1
                if not self.infinite:
                    return
        finally:
            self.close()

    def _make(self, path: str, frame_id: str, rng: np.random.Generator) -> tuple:
        left, right, label, label_right, confidence, confidence_right = self._read(path, frame_id)
        weight = confidence if self.with_confidence else None
        if self.transform is not None:
            left, right, label, *rest = self.transform(left, right, label, label_right, rng, weight=weight,
                                                       weight_right=confidence_right)
            weight = rest[0] if rest else None
        else:
            h, w = left.shape[0] // 8 * 8, left.shape[1] // 8 * 8
            left, right, label = left[:h, :w], right[:h, :w], label[:h, :w]
            weight = None if weight is None else weight[:h, :w]
        out = to_tensors(left, right, label, self.max_disp)
        if weight is not None:
            out = (*out, torch.from_numpy(np.ascontiguousarray(weight, dtype=np.float32))[None])
        return (*out, frame_id) if self.with_ids else out
