"""ShardStream and the joint transforms: work split, determinism, resume skipping, formats, clear failures."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import make_shards, make_synthetic_pair
from torch.utils.data import DataLoader

from optstereo.data import ShardStream, TrainTransform, collate_min_size, to_tensors
from optstereo.data.stream import shuffle_buffer, skip_count
from optstereo.data.transforms import crop_window, photometric_jitter
from pvm_labeler.common.errors import ShardError
from pvm_labeler.shards import ShardRecord, write_shard_dir


def ids_of(stream: ShardStream) -> list[str]:
    return [item[-1] for item in stream]


def stream(path: Path, **kw) -> ShardStream:
    kw.setdefault("infinite", False)
    kw.setdefault("with_ids", True)
    return ShardStream(path, **kw)


@pytest.fixture
def shards(tmp_path: Path) -> Path:
    return make_shards(tmp_path / "shards", n=8, shard_size=2)


class TestSplit:
    def test_ranks_get_disjoint_shards(self, shards: Path) -> None:
        seen = [ids_of(stream(shards, rank=r, world_size=2)) for r in range(2)]
        assert set(seen[0]).isdisjoint(seen[1])
        assert sorted(seen[0] + seen[1]) == [f"frame-{i:03d}" for i in range(8)]
        # 4 shards of 2 samples over 2 ranks: whole shards per rank (shard index g, g + 2).
        assert sorted(seen[0]) == ["frame-000", "frame-001", "frame-004", "frame-005"]

    def test_fewer_shards_than_workers_splits_samples(self, tmp_path: Path) -> None:
        path = make_shards(tmp_path / "one", n=4, shard_size=4)
        seen = [ids_of(stream(path, rank=r, world_size=2)) for r in range(2)]
        assert sorted(seen[0]) == ["frame-000", "frame-002"]
        assert sorted(seen[1]) == ["frame-001", "frame-003"]

    def test_fewer_samples_than_workers_still_feeds_every_rank(self, tmp_path: Path) -> None:
        path = make_shards(tmp_path / "tiny", n=1, shard_size=1)
        assert [ids_of(stream(path, rank=r, world_size=3)) for r in range(3)] == [["frame-000"]] * 3

    def test_dataloader_workers_cover_each_sample_once(self, shards: Path) -> None:
        loader = DataLoader(stream(shards, transform=None), batch_size=1, num_workers=2)
        ids = [batch[-1][0] for batch in loader]
        assert sorted(ids) == [f"frame-{i:03d}" for i in range(8)]

    def test_skip_count_round_robin(self) -> None:
        # 5 batches over 2 workers: worker 0 made batches 0, 2, 4; worker 1 made 1, 3.
        assert skip_count(5, 3, 0, 2) == 9
        assert skip_count(5, 3, 1, 2) == 6
        assert skip_count(5, 3, 0, 0) == 15


class TestOrder:
    def test_shuffle_buffer_is_a_seeded_permutation(self) -> None:
        items = [(str(i), str(i)) for i in range(50)]
        a = list(shuffle_buffer(items, 8, np.random.default_rng(1)))
        b = list(shuffle_buffer(items, 8, np.random.default_rng(1)))
        c = list(shuffle_buffer(items, 8, np.random.default_rng(2)))
        assert sorted(a, key=lambda k: int(k[0])) == items and a == b and a != c and a != items

    def test_seed_determines_order_and_epochs_differ(self, shards: Path) -> None:
        s1 = stream(shards, seed=3, shuffle_size=4)
        s2 = stream(shards, seed=3, shuffle_size=4)
        assert ids_of(s1) == ids_of(s2)
        assert s1.epoch_order(0, 0, 1) != s1.epoch_order(1, 0, 1)
        assert ids_of(stream(shards, seed=4, shuffle_size=4)) != ids_of(s1)

    def test_an_infinite_stream_draws_every_sample_alike_over_unequal_workers(self, tmp_path: Path) -> None:
        """5 samples in shards of 2 + 2 + 1 over 2 workers: each worker held its shards and the DataLoader takes
        the workers in turn, so the two frames of the 2-sample worker came round 1.5x as often (50 vs 33 in 100
        batches). Each worker now yields ceil(5 / 2) samples of one seeded order per epoch."""
        shards = make_shards(tmp_path / "s", n=5, shard_size=2)
        s = ShardStream(shards, infinite=True, shuffle_size=1)
        counts: dict[str, int] = {}
        for epoch in range(600):
            for worker in range(2):
                block = s.epoch_order(epoch, worker, 2)
                assert len(block) == 3 and len({k[0] for k in block}) <= 3  # whole shards, in order
                for _, fid in block:
                    counts[fid] = counts.get(fid, 0) + 1
        assert len(counts) == 5 and sum(counts.values()) == 3600
        assert max(counts.values()) / min(counts.values()) < 1.1, counts  # was 1.5
        one_epoch = [ids_of(stream(shards, rank=0, world_size=1, seed=s.seed))]  # not infinite: each sample once
        assert sorted(one_epoch[0]) == sorted(counts)

    @pytest.mark.parametrize("workers", [0, 2])
    def test_skip_batches_resumes_the_same_stream(self, shards: Path, workers: int) -> None:
        def batches(skip: int, count: int) -> list:
            s = ShardStream(shards, transform=TrainTransform(crop=(16, 32), photometric=True), seed=5,
                            shuffle_size=4, with_ids=True, skip_batches=skip, batch_size=2)
            it = iter(DataLoader(s, batch_size=2, num_workers=workers, collate_fn=collate_min_size))
            return [next(it) for _ in range(count)]

        full, resumed = batches(0, 7), batches(3, 4)
        for a, b in zip(full[3:], resumed, strict=True):
            assert a[-1] == b[-1]
            for x, y in zip(a[:4], b[:4], strict=True):
                assert torch.equal(x, y)  # same ids AND same random crops/jitter


class TestSamples:
    def test_tuple_order_types_and_valid_mask(self, shards: Path) -> None:
        left, right, label, valid, frame_id = next(iter(stream(shards, transform=None, shuffle_size=1)))
        assert left.shape == right.shape == (3, 32, 64) and left.dtype == torch.float32
        assert label.shape == valid.shape == (1, 32, 64) and valid.dtype == torch.bool
        i = int(frame_id[-3:])
        assert torch.allclose(label[valid], torch.tensor(4 + i / 100))
        assert not valid[..., :4].any() and valid[..., 4:].all() and (label[~valid] == 0).all()
        assert float(left.max()) > 1.0  # [0, 255], not normalised

    def test_left_matches_right_shifted(self, shards: Path) -> None:
        left, right, *_ = next(iter(stream(shards, transform=None)))
        assert torch.equal(left[..., 4:], right[..., :-4])  # left(x) == right(x - 4)

    def test_flip_swap_uses_right_label(self, shards: Path) -> None:
        tf = TrainTransform(crop=(32, 64), flip_swap_p=1.0)
        left, right, label, valid, frame_id = next(iter(stream(shards, transform=tf)))
        i = int(frame_id[-3:])
        assert torch.allclose(label[valid], torch.tensor(4.5 + i / 100))  # the flipped RIGHT-view label
        assert not valid[..., :4].any()  # its NaN band (right edge) moved to the left edge
        assert torch.equal(left[..., 4:], right[..., :-4])  # still positive disparity after mirroring

    def test_gt_supervision_reads_gt(self, shards: Path) -> None:
        _, _, label, valid, _ = next(iter(stream(shards, transform=None, supervision="gt")))
        assert valid.all() and torch.all(label == 4.0)

    def test_crop_size(self, shards: Path) -> None:
        left, _, label, _, _ = next(iter(stream(shards, transform=TrainTransform(crop=(16, 40)))))
        assert left.shape == (3, 16, 40) and label.shape == (1, 16, 40)
        # Crop larger than the frame: the whole frame (rounded down to multiples of 8).
        left, *_ = next(iter(stream(shards, transform=TrainTransform(crop=(320, 736)))))
        assert left.shape == (3, 32, 64)


class TestErrors:
    def test_gt_supervision_without_gt_names_the_shard(self, tmp_path: Path) -> None:
        path = make_shards(tmp_path / "nogt", n=2, with_gt=False)
        with pytest.raises(ShardError, match=r"shard-00000\.h5.*no 'gt'|no 'gt'.*shard-00000\.h5"):
            next(iter(stream(path, supervision="gt")))

    def test_wrong_schema_version(self, shards: Path) -> None:
        index = json.loads((shards / "index.json").read_text())
        index["schema"]["version"] = 99
        (shards / "index.json").write_text(json.dumps(index))
        with pytest.raises(ShardError, match="version 99"):
            ShardStream(shards)

    def test_empty_directory(self, tmp_path: Path) -> None:
        with pytest.raises(ShardError, match="index"):
            ShardStream(tmp_path)

    def test_empty_index(self, shards: Path) -> None:
        index = json.loads((shards / "index.json").read_text())
        index.update(shards=[], num_samples=0)
        (shards / "index.json").write_text(json.dumps(index))
        with pytest.raises(ShardError, match="no samples"):
            ShardStream(shards)

    def test_corrupt_shard_fails_lazily_naming_it(self, shards: Path) -> None:
        bad = shards / "shard-00001.h5"
        bad.write_bytes(bad.read_bytes()[:100])  # truncated
        s = stream(shards, shuffle_size=1, seed=0)  # __init__ never opens h5 files
        with pytest.raises(ShardError, match="shard-00001.h5"):
            list(s)


class TestTransforms:
    def test_crop_window_bounds(self, rng: np.random.Generator) -> None:
        for _ in range(20):
            y0, x0, h, w = crop_window(375, 1242, (320, 736), rng)
            assert (h, w) == (320, 736) and 0 <= y0 <= 55 and 0 <= x0 <= 506
        assert crop_window(375, 1242, (512, 1024), rng)[2:] == (368, 1024)
        with pytest.raises(ValueError, match="smaller"):
            crop_window(5, 100, (8, 8), rng)

    def test_photometric_jitter_keeps_matching_structure(self, rng: np.random.Generator) -> None:
        left, right = make_synthetic_pair(rng, 32, 64, 4)
        jl, jr = photometric_jitter(left, right, np.random.default_rng(0))
        assert jl.shape == left.shape and jl.dtype == np.uint8 and not np.array_equal(jl, left)
        # Shared jitter + a <= 5 % per-view gain: corresponding pixels stay strongly correlated.
        corr = np.corrcoef(jl[:, 4:].ravel().astype(float), jr[:, :-4].ravel().astype(float))[0, 1]
        assert corr > 0.95

    def test_to_tensors_masks_out_of_range(self) -> None:
        label = np.array([[np.nan, -1.0, 3.0, 300.0]], np.float32)
        img = np.zeros((1, 4, 3), np.uint8)
        _, _, lab, valid = to_tensors(img, img, label, max_disp=256)
        assert valid.tolist() == [[[False, False, True, False]]] and lab.tolist() == [[[0.0, 0.0, 3.0, 0.0]]]

    def test_collate_trims_to_smallest(self) -> None:
        a = (torch.zeros(3, 16, 32), torch.zeros(3, 16, 32), torch.zeros(1, 16, 32), torch.ones(1, 16, 32, dtype=bool))
        b = (torch.zeros(3, 24, 24), torch.zeros(3, 24, 24), torch.zeros(1, 24, 24), torch.ones(1, 24, 24, dtype=bool))
        batch = collate_min_size([a, b])
        assert batch[0].shape == (2, 3, 16, 24) and batch[3].shape == (2, 1, 16, 24)


def test_stream_with_confidence_crops_it_like_the_label(tmp_path: Path) -> None:
    shards = make_shards(tmp_path / "s", n=2, shard_size=2, height=32, width=64)
    plain = list(stream(shards, transform=TrainTransform(crop=(16, 40), flip_swap_p=0.0), with_ids=False))
    weighted = list(stream(shards, transform=TrainTransform(crop=(16, 40), flip_swap_p=0.0), with_ids=False,
                           with_confidence=True))
    for (l0, _, lab0, _v0), (l1, _, lab1, v1, w1) in zip(plain, weighted, strict=True):
        assert torch.equal(l0, l1) and torch.equal(lab0, lab1)  # same random draws with or without the weight
        assert w1.shape == lab1.shape
        assert torch.equal(w1 > 0, v1)  # make_shards' confidence is 1 on labelled pixels, 0 elsewhere
    flipped = next(iter(stream(shards, transform=TrainTransform(crop=(16, 40), flip_swap_p=1.0), with_ids=False,
                               with_confidence=True)))
    assert torch.equal(flipped[4], torch.ones_like(flipped[4]))  # no right-view confidence: weight 1


def test_flip_swapped_samples_take_the_right_views_confidence_mirrored(tmp_path: Path) -> None:
    # A right-view confidence that varies along x (0.01 * x on labels) shows both its use and its mirroring.
    rng = np.random.default_rng(3)
    left, right = make_synthetic_pair(rng, 16, 40, 4)
    label, label_right = np.full((16, 40), 4.0, np.float32), np.full((16, 40), 4.5, np.float32)
    conf_right = np.broadcast_to(np.arange(40, dtype=np.float32) / 100, (16, 40)).copy()
    record = ShardRecord("f", left, right, label, label_right, np.full((16, 40), 0.7, np.float32),
                         confidence_right=conf_right)
    shards = write_shard_dir(tmp_path / "s", [record], config={"k": 1})
    items = [next(iter(stream(shards, transform=TrainTransform(crop=(16, 40), flip_swap_p=p), with_ids=False,
                              with_confidence=True))) for p in (1.0, 0.0)]
    flipped, kept = items[0][4][0], items[1][4][0]
    assert torch.equal(items[0][2][0], torch.full((16, 40), 4.5))  # the right label, flip-swapped
    # float16 on disk: 0.01 * x within half a float16 step
    torch.testing.assert_close(flipped, torch.from_numpy(conf_right[:, ::-1].copy()), atol=2e-4, rtol=0)
    assert torch.equal(kept, torch.full((16, 40), 0.7, dtype=torch.float16).float())


def test_unflippable_samples_are_counted_and_warned_once(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """GT shards without gt_right: flip-swap cannot apply to any sample; PVM shards always have label_right."""
    from optstereo.distributed import DistInfo
    from optstereo.training.loop import _warn_unflippable

    shards = make_shards(tmp_path / "s", n=5, shard_size=2)
    gt_stream = ShardStream(shards, supervision="gt")
    assert gt_stream.count_unflippable() == 5
    assert ShardStream(shards, supervision="pvm").count_unflippable() == 0
    caplog.set_level(logging.WARNING, logger="optstereo.training.loop")
    _warn_unflippable(gt_stream, 0.5, DistInfo(0, 1, 0).is_main)
    _warn_unflippable(gt_stream, 0.0, True)  # flip-swap off: nothing to say
    warnings = [r.getMessage() for r in caplog.records if "flip-swap" in r.getMessage()]
    assert len(warnings) == 1 and "cannot flip 5 of 5 samples" in warnings[0] and "gt_right" in warnings[0]
