"""Shard schema: round trip, atomic writes, index checks, verify() naming broken shards."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from hdf5plugin import BLOSC_ID

from pvm_labeler.common.errors import ShardError
from pvm_labeler.shards import (
    COMPRESSIONS,
    INDEX_NAME,
    SCHEMA_NAME,
    SCHEMA_VERSION,
    ShardRecord,
    ShardWriter,
    open_shard,
    read_index,
    read_sample,
    verify,
    write_shard_dir,
)


def make_record(rng: np.random.Generator, frame_id: str, shape: tuple[int, int], with_gt: bool = True) -> ShardRecord:
    label = rng.uniform(0, 50, shape).astype(np.float32)
    label[rng.random(shape) < 0.4] = np.nan
    gt = rng.uniform(0, 50, shape).astype(np.float32) if with_gt else None
    if gt is not None:
        gt[0, :] = np.nan
    return ShardRecord(
        frame_id=frame_id,
        left=rng.integers(0, 256, (*shape, 3), dtype=np.uint8),
        right=rng.integers(0, 256, (*shape, 3), dtype=np.uint8),
        label=label,
        label_right=label[:, ::-1].copy(),
        confidence=rng.random(shape).astype(np.float32),
        gt=gt,
        gt_noc=None,
        gt_right=gt,
        attrs={"sources": {"left": "/x/l.png"}, "eps": np.array([0.0, 0.3]), "factors": np.array([1.0, 2.3]),
               "seed": 7},
    )


@pytest.fixture
def shard_dir(tmp_path: Path, rng: np.random.Generator) -> tuple[Path, list[ShardRecord]]:
    # Frames differ in size on purpose (KITTI: 1242x375, 1241x376, ...).
    records = [make_record(rng, f"f{i}", (20 + i, 30 - i), with_gt=i != 2) for i in range(5)]
    out = write_shard_dir(tmp_path / "shards", records, config={"k": 3, "kappa1": 1.0}, dataset={"name": "t"},
                          shard_size=2)
    return out, records


class TestRoundTrip:
    def test_index(self, shard_dir: tuple[Path, list[ShardRecord]]) -> None:
        out, _ = shard_dir
        index = read_index(out)
        assert index.num_samples == 5 and index.config == {"k": 3, "kappa1": 1.0}
        assert [p.name for p, _ in index.shards] == ["shard-00000.h5", "shard-00001.h5", "shard-00002.h5"]
        assert [ids for _, ids in index.shards] == [["f0", "f1"], ["f2", "f3"], ["f4"]]
        doc = json.loads((out / INDEX_NAME).read_text())
        assert doc["schema"] == {"name": SCHEMA_NAME, "version": SCHEMA_VERSION}
        assert "git_commit" in doc and "code_version" in doc and doc["dataset"] == {"name": "t"}

    def test_samples_exact(self, shard_dir: tuple[Path, list[ShardRecord]]) -> None:
        out, records = shard_dir
        index = read_index(out)
        got = {}
        for path, ids in index.shards:
            with open_shard(path) as h5:
                assert h5.attrs["schema_version"] == SCHEMA_VERSION
                for frame_id in ids:
                    got[frame_id] = read_sample(h5, frame_id)
        for rec in records:
            s = got[rec.frame_id]
            np.testing.assert_array_equal(s.left, rec.left)
            np.testing.assert_array_equal(s.right, rec.right)
            np.testing.assert_array_equal(s.label, rec.label)  # NaN positions equal too
            np.testing.assert_array_equal(s.label_right, rec.label_right)
            assert s.confidence.dtype == np.float32
            np.testing.assert_allclose(s.confidence, rec.confidence, atol=5e-4)  # float16 storage
            if rec.gt is None:
                assert s.gt is None and s.gt_right is None
            else:
                np.testing.assert_array_equal(s.gt, rec.gt)
            assert s.gt_noc is None
            assert s.attrs["seed"] == 7 and s.attrs["sources"] == {"left": "/x/l.png"}
            np.testing.assert_array_equal(s.attrs["eps"], [0.0, 0.3])

    def test_layout_chunked_compressed(self, shard_dir: tuple[Path, list[ShardRecord]]) -> None:
        out, _ = shard_dir
        with h5py.File(out / "shard-00000.h5", "r") as h5:
            dset = h5["f0/label"]
            assert dset.chunks is not None
            plist = dset.id.get_create_plist()
            filters = [plist.get_filter(i)[0] for i in range(plist.get_nfilters())]
            assert filters == [BLOSC_ID, h5py.h5z.FILTER_FLETCHER32]  # Blosc-LZ4 + shuffle (hdf5plugin), a checksum
            assert h5["f0/confidence"].dtype == np.float16 and h5["f0/left"].dtype == np.uint8

    @pytest.mark.parametrize("compression", COMPRESSIONS)
    def test_every_compression_exact(self, tmp_path: Path, rng: np.random.Generator, compression: str) -> None:
        rec = make_record(rng, "a", (37, 53))
        out = write_shard_dir(tmp_path / "s", [rec], config={}, shard_size=1, compression=compression)
        with open_shard(out / "shard-00000.h5") as h5:
            assert h5.attrs["compression"] == compression
            got = read_sample(h5, "a")
        for name in ("left", "right", "label", "label_right", "gt"):
            np.testing.assert_array_equal(getattr(got, name), getattr(rec, name), err_msg=f"{compression} {name}")

    def test_unknown_compression(self, tmp_path: Path) -> None:
        with pytest.raises(ShardError, match="unknown compression 'brotli'"):
            ShardWriter(tmp_path / "s.h5", {}, compression="brotli")

    def test_verify_ok(self, shard_dir: tuple[Path, list[ShardRecord]]) -> None:
        assert verify(shard_dir[0]) == []


class TestAtomic:
    def test_exception_leaves_nothing(self, tmp_path: Path, rng: np.random.Generator) -> None:
        path = tmp_path / "shard-00000.h5"
        with pytest.raises(RuntimeError), ShardWriter(path, {"k": 2}) as writer:
            writer.add(make_record(rng, "a", (8, 8)))
            # the shard is built in memory: nothing is on disk before close() (issue 51's full-disk fix)
            assert not writer.tmp_path.exists() and not path.exists()
            raise RuntimeError("worker died")
        assert list(tmp_path.iterdir()) == []

    def test_bad_record(self, tmp_path: Path, rng: np.random.Generator) -> None:
        rec = make_record(rng, "a", (8, 8))
        rec.label = rec.label[:, :5]
        match = r"sample a: 'label' must be float32 .* size \(8, 8\), got float32 \(8, 5\)"
        with pytest.raises(ShardError, match=match):
            with ShardWriter(tmp_path / "s.h5", {}) as writer:
                writer.add(rec)
        assert list(tmp_path.iterdir()) == []


class TestErrors:
    def test_missing_index(self, tmp_path: Path) -> None:
        with pytest.raises(ShardError, match=f"no shard index at {tmp_path / INDEX_NAME}"):
            read_index(tmp_path)

    def test_wrong_version(self, shard_dir: tuple[Path, list[ShardRecord]]) -> None:
        out, _ = shard_dir
        doc = json.loads((out / INDEX_NAME).read_text())
        doc["schema"]["version"] = 99
        (out / INDEX_NAME).write_text(json.dumps(doc))
        with pytest.raises(ShardError, match="schema version 99, this code reads version 1"):
            read_index(out)
        doc["schema"]["name"] = "something-else"
        (out / INDEX_NAME).write_text(json.dumps(doc))
        with pytest.raises(ShardError, match="schema name 'something-else'"):
            read_index(out)

    def test_missing_shard_file(self, shard_dir: tuple[Path, list[ShardRecord]]) -> None:
        out, _ = shard_dir
        (out / "shard-00001.h5").unlink()
        with pytest.raises(ShardError, match="shard-00001.h5, which does not exist"):
            read_index(out)
        assert any("shard-00001.h5" in p for p in verify(out))

    def test_truncated_shard(self, shard_dir: tuple[Path, list[ShardRecord]]) -> None:
        out, _ = shard_dir
        path = out / "shard-00001.h5"
        path.write_bytes(path.read_bytes()[:3000])
        with pytest.raises(ShardError, match="corrupt or truncated shard .*shard-00001.h5"):
            open_shard(path)
        problems = verify(out)
        assert len(problems) == 1 and "shard-00001.h5" in problems[0]

    def test_shard_wrong_schema_attrs(self, shard_dir: tuple[Path, list[ShardRecord]]) -> None:
        out, _ = shard_dir
        with h5py.File(out / "shard-00002.h5", "a") as h5:
            h5.attrs["schema_version"] = 2
        with pytest.raises(ShardError, match="shard-00002.h5: schema 'pvstereo-pvm-shards' version 2"):
            open_shard(out / "shard-00002.h5")

    def test_verify_count_and_tmp(self, shard_dir: tuple[Path, list[ShardRecord]]) -> None:
        out, _ = shard_dir
        doc = json.loads((out / INDEX_NAME).read_text())
        doc["shards"][0]["samples"] = ["f0", "f9"]
        (out / INDEX_NAME).write_text(json.dumps(doc))
        (out / "shard-00003.h5.tmp").write_bytes(b"partial")
        problems = verify(out)
        assert any("shard-00000.h5: holds samples ['f0', 'f1'], index lists ['f0', 'f9']" in p for p in problems)
        assert any("stale temporary file" in p and "shard-00003.h5.tmp" in p for p in problems)

    def test_verify_an_index_of_no_samples(self, shard_dir: tuple[Path, list[ShardRecord]]) -> None:
        """An index listing nothing (every pair failed) read "ok: 0 samples" while the trainer refuses it."""
        out, _ = shard_dir
        doc = json.loads((out / INDEX_NAME).read_text())
        doc.update(shards=[], num_samples=0)
        (out / INDEX_NAME).write_text(json.dumps(doc))
        assert verify(out) == [f"{out / INDEX_NAME}: lists no samples (nothing to train on; every pair failed?)"]

    def test_corrupt_dataset_named(self, shard_dir: tuple[Path, list[ShardRecord]]) -> None:
        out, _ = shard_dir
        with h5py.File(out / "shard-00001.h5", "a") as h5:
            del h5["f3/label_right"]
        problems = verify(out)
        assert problems == [f"shard {out / 'shard-00001.h5'}: sample 'f3' lacks ['label_right']"]


def test_convert_to_lzf_round_trips_every_array(tmp_path: Path) -> None:
    from click.testing import CliRunner
    from conftest import make_shards

    from pvm_labeler.cli import main as pvm_main

    src = make_shards(tmp_path / "src", n=3, shard_size=2)  # Blosc-LZ4, the default
    result = CliRunner().invoke(pvm_main, ["convert", str(src), str(tmp_path / "lzf"), "--compression", "lzf"])
    assert result.exit_code == 0, result.output
    out = tmp_path / "lzf"
    assert verify(out) == []
    a, b = read_index(src), read_index(out)
    assert [ids for _, ids in a.shards] == [ids for _, ids in b.shards] and a.config == b.config
    for (pa, ids), (pb, _) in zip(a.shards, b.shards, strict=True):
        with open_shard(pa) as ha, open_shard(pb) as hb:
            assert hb.attrs["compression"] == "lzf" and hb[ids[0]]["left"].compression == "lzf"
            for fid in ids:
                sa, sb = read_sample(ha, fid), read_sample(hb, fid)
                for name in ("left", "right", "label", "label_right", "confidence", "gt"):
                    np.testing.assert_array_equal(getattr(sa, name), getattr(sb, name))
                assert sa.attrs == sb.attrs
    same = CliRunner().invoke(pvm_main, ["convert", str(src), str(src)])
    assert same.exit_code == 1 and "must differ" in same.output


def test_frame_ids_and_confidences_a_shard_cannot_hold_are_refused(tmp_path: Path, rng: np.random.Generator) -> None:
    """'seq1/000' became a nested HDF5 group that verify then called broken; '' a bare h5py error; a confidence x3
    and one frame in two shards passed verify."""
    for fid in ("seq1/000", "", ".."):
        with pytest.raises(ShardError, match="cannot name a sample"):
            write_shard_dir(tmp_path / f"s{len(fid)}", [make_record(rng, fid, (8, 16))], config={})
    tripled = make_record(rng, "a", (8, 16))
    tripled.confidence[:] = 3.0
    with pytest.raises(ShardError, match=r"'confidence' must lie in \[0, 1\], got 3"):
        write_shard_dir(tmp_path / "c", [tripled], config={})
    out = write_shard_dir(tmp_path / "d", [make_record(rng, "a", (8, 16)), make_record(rng, "b", (8, 16))],
                          config={}, shard_size=1)
    index = json.loads((out / "index.json").read_text())
    index["shards"][1]["samples"] = ["a"]  # shard 1 holds b; index says a: and a twice
    (out / "index.json").write_text(json.dumps(index))
    assert any("frame 'a' is in shard-00000.h5 and shard-00001.h5" in p for p in verify(out))
