"""pvm_labeler/densify.py: the plane fill on hand-made maps, and `pvm-label densify` on a shard directory."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from pvm_labeler.cli import main as pvm_main
from pvm_labeler.densify import densify, densify_view, fill_planes, plane_fill
from pvm_labeler.shards import (
    ShardRecord,
    open_shard,
    read_index,
    read_sample,
    shard_sample_ids,
    verify,
    write_shard_dir,
)

N = np.nan


def slanted(h: int = 12, w: int = 16) -> np.ndarray:
    ys, xs = np.mgrid[0:h, 0:w]
    return (20 + 0.5 * xs - 0.25 * ys).astype(np.float32)


def test_fill_planes_recovers_a_slanted_plane_in_the_holes_only() -> None:
    plane = slanted()
    label = plane.copy()
    label[3:8, 4:12] = N  # a hole inside one segment
    out = fill_planes(np.zeros(plane.shape, np.int32), label, max_rms=0.1)
    hole = np.isnan(label)
    np.testing.assert_allclose(out[hole], plane[hole], atol=1e-4)
    assert np.isnan(out[~hole]).all()  # labelled pixels are not part of what is added


def test_fill_planes_rejects_poor_fits_and_sparse_segments() -> None:
    plane = slanted()
    rng = np.random.default_rng(0)
    label = plane + rng.normal(0, 2.0, plane.shape).astype(np.float32)  # RMS ~2 px: not a plane
    label[:, 1:8:2] = N  # segment 0 (columns 0-7): half labelled
    segments = np.zeros(plane.shape, np.int32)
    segments[:, 8:] = 1
    label[:, 8:] = N
    label[0, 8:13] = plane[0, 8:13]  # segment 1: 5 labels out of 96, under MIN_LABELS and MIN_RATIO
    out = fill_planes(segments, label, max_rms=0.5)
    assert np.isnan(out).all()
    # The same noisy segment 0 is filled once the RMS bound allows it.
    assert np.isfinite(fill_planes(segments, label, max_rms=5.0)[:, :8][np.isnan(label[:, :8])]).all()


def test_fill_planes_fits_each_segment_separately() -> None:
    """Two segments on two different planes: each hole takes its own segment's plane."""
    left, right = slanted(), np.full((12, 16), 7.0, np.float32)
    segments = np.zeros((12, 16), np.int32)
    segments[:, 8:] = 3
    truth = np.where(segments == 0, left, right)
    label = truth.copy()
    label[5, 2] = label[6, 12] = N
    out = fill_planes(segments, label, max_rms=0.1)
    np.testing.assert_allclose([out[5, 2], out[6, 12]], [left[5, 2], 7.0], atol=1e-4)


def test_plane_fill_on_an_image() -> None:
    """SLIC runs on an RGB image; a constant-disparity label with one hole fills it with the constant."""
    rng = np.random.default_rng(1)
    image = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
    label = np.full((24, 32), 9.0, np.float32)
    label[10, 10] = N
    out = plane_fill(image, label, region_size=8, max_rms=0.1)
    assert out[10, 10] == pytest.approx(9.0, abs=1e-4) and np.isfinite(out).sum() == 1


def test_densify_view_drops_fills_at_or_below_zero() -> None:
    """A plane falling through 0 px (toward the horizon): only its positive fills are kept, at fill_confidence."""
    image = np.full((16, 32, 3), 128, np.uint8)
    truth = (np.arange(32, dtype=np.float32) - 8)[None].repeat(16, 0)  # -8 .. 23 px along x
    label = np.where(truth > 0.5, truth, N).astype(np.float32)
    label[4:12, 20:24] = N  # an inner hole, on positive disparities
    conf = np.where(np.isfinite(label), 0.9, 0).astype(np.float32)
    dense, new_conf, n = densify_view(image, label, conf, region_size=16, max_rms=0.1, fill_confidence=0.5)
    np.testing.assert_allclose(dense[4:12, 20:24], truth[4:12, 20:24], atol=1e-3)
    assert np.isnan(dense[truth <= 0]).all() and n == int((np.isfinite(dense) & np.isnan(label)).sum())
    assert (new_conf[4:12, 20:24] == 0.5).all() and (new_conf[np.isfinite(label)] == np.float32(0.9)).all()


def _record(frame_id: str, hole: tuple[slice, slice]) -> tuple[ShardRecord, np.ndarray]:
    h, w = 32, 48
    ys, xs = np.mgrid[0:h, 0:w]
    plane = (30 + 0.2 * xs + 0.1 * ys).astype(np.float32)
    label = plane.copy()
    label[hole] = N
    img = np.full((h, w, 3), 100, np.uint8)
    conf = np.where(np.isfinite(label), 0.8, 0).astype(np.float16)
    return ShardRecord(frame_id=frame_id, left=img, right=img.copy(), label=label, label_right=label.copy(),
                       confidence=conf, gt=plane), plane


def test_densify_rewrites_a_shard_directory(tmp_path: Path) -> None:
    hole = (slice(10, 14), slice(20, 26))
    records, planes = zip(*(_record(f"f{i}", hole) for i in range(3)), strict=True)
    src = write_shard_dir(tmp_path / "src", records, {"k": 6}, shard_size=2)
    result = CliRunner().invoke(pvm_main, ["densify", str(src), str(tmp_path / "dense"), "--region-size", "8",
                                           "--max-rms", "0.1", "--fill-confidence", "0.25"])
    assert result.exit_code == 0, result.output
    out = tmp_path / "dense"
    assert verify(out) == []
    index = read_index(out)
    assert index.config == {"k": 6} and index.raw["densify"]["fill_confidence"] == 0.25
    assert index.raw["densified_from"] == str(src)
    for (path, ids), ((src_path, _)) in zip(index.shards, read_index(src).shards, strict=True):
        with open_shard(path) as h5, open_shard(src_path) as h5_src:
            for fid in ids:
                new, old = read_sample(h5, fid), read_sample(h5_src, fid)
                plane = planes[int(fid[1:])]
                for label in (new.label, new.label_right):
                    np.testing.assert_allclose(label[hole], plane[hole], atol=1e-3)
                    np.testing.assert_array_equal(label[np.isfinite(old.label)], old.label[np.isfinite(old.label)])
                assert (new.confidence[hole] == 0.25).all()
                # The right view's weights: the fill confidence on its fills, 1 on PVM's right labels.
                assert (new.confidence_right[hole] == 0.25).all()
                assert (new.confidence_right[np.isfinite(old.label_right)] == 1).all()
                np.testing.assert_array_equal(new.confidence[np.isfinite(old.label)],
                                              old.confidence[np.isfinite(old.label)])
                np.testing.assert_array_equal(new.left, old.left)
                np.testing.assert_array_equal(new.gt, old.gt)
                assert new.attrs["densify_filled_left"] == new.attrs["densify_filled_right"] == 24


def test_densify_checks_its_arguments(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="fill_confidence"):
        densify(tmp_path, tmp_path / "out", fill_confidence=0)
    bad = CliRunner().invoke(pvm_main, ["densify", str(tmp_path), str(tmp_path / "o"), "--max-rms", "0"])
    assert bad.exit_code == 2 and "max-rms" in bad.output
    ignored = CliRunner().invoke(pvm_main, ["densify", str(tmp_path), str(tmp_path / "o"), "--views", "left"])
    assert ignored.exit_code == 2 and "--method planes fills both views" in ignored.output  # it was ignored
    assert not (tmp_path / "o").exists()


def _interrupted(monkeypatch: pytest.MonkeyPatch, src: Path, out: Path, fail_at: int, **kwargs: float) -> None:
    """Run densify with the view densifier failing at its ``fail_at``-th call (an interruption)."""
    import pvm_labeler.densify as module

    real, calls = module.densify_view, []

    def failing(*args: object) -> object:
        calls.append(1)
        if len(calls) == fail_at:
            raise RuntimeError("interrupted")
        return real(*args)

    monkeypatch.setattr(module, "densify_view", failing)
    with pytest.raises(RuntimeError, match="interrupted"):
        densify(src, out, **kwargs)
    monkeypatch.setattr(module, "densify_view", real)


def _count_calls(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    import pvm_labeler.densify as module

    real, calls = module.densify_view, []

    def counting(*args: object) -> object:
        calls.append(1)
        return real(*args)

    monkeypatch.setattr(module, "densify_view", counting)
    return calls


def test_an_interrupted_densify_resumes_only_the_same_settings(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from pvm_labeler.common.errors import ShardError

    hole = (slice(10, 14), slice(20, 26))
    records = [_record(f"f{i}", hole)[0] for i in range(3)]
    src = write_shard_dir(tmp_path / "src", records, {"k": 6}, shard_size=2)  # shards: [f0, f1], [f2]
    out, settings = tmp_path / "dense", {"region_size": 8, "max_rms": 0.1}
    _interrupted(monkeypatch, src, out, fail_at=5, **settings)  # 2 calls per pair: dies on f2
    with pytest.raises(ShardError):
        read_index(out)  # never looks complete
    assert (out / "shard-00000.h5").exists() and not (out / "shard-00001.h5").exists()
    calls = _count_calls(monkeypatch)
    densify(src, out, **settings)
    assert len(calls) == 2 and verify(out) == []  # only f2 was densified again
    clean = densify(src, tmp_path / "clean", **settings)
    for name in ("shard-00000.h5", "shard-00001.h5"):
        with open_shard(out / name) as a, open_shard(clean / name) as b:
            for fid in shard_sample_ids(a):
                np.testing.assert_array_equal(read_sample(a, fid).label, read_sample(b, fid).label)
    # A new rewrite into the finished OUT, interrupted: the old index must not make it look complete.
    _interrupted(monkeypatch, src, out, fail_at=1, region_size=8, max_rms=0.3)
    with pytest.raises(ShardError):
        read_index(out)
    # ... and its re-run redoes every shard: the finished rewrite's (max_rms 0.1) passed for this one's and were kept
    calls = _count_calls(monkeypatch)
    densify(src, out, region_size=8, max_rms=0.3)
    assert len(calls) == 6 and verify(out) == []
    # Interrupted again, then re-run with another setting: everything is redone.
    _interrupted(monkeypatch, src, tmp_path / "dense2", fail_at=5, **settings)
    calls = _count_calls(monkeypatch)
    densify(src, tmp_path / "dense2", region_size=8, max_rms=0.2)
    assert len(calls) == 6 and read_index(tmp_path / "dense2").raw["densify"]["max_rms"] == 0.2


def test_sgm_method_fills_the_left_view_from_filtered_sgm(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    # The left view's holes take exactly the weighted median of the row-filled dense SGM (a fake matcher here: a
    # known map with NaN streaks and one non-positive value); labels, the right view and the images stay.
    import pvm_labeler.dense as dense
    from pvm_labeler.refine import weighted_median

    hole = (slice(10, 14), slice(20, 26))
    records, _ = zip(*(_record(f"f{i}", hole) for i in range(2)), strict=True)
    src = write_shard_dir(tmp_path / "src", records, {"k": 6, "max_disp": 64}, shard_size=2)
    h, w = records[0].label.shape
    sgm = (5.0 + np.arange(w, dtype=np.float32) / 10)[None].repeat(h, 0)
    sgm[11, 18:23] = np.nan  # a streak the row fill closes
    sgm[13:] = -1.0  # a region the median keeps negative: its hole pixels (row 13) stay empty
    seen = []

    def fake_sgm_left(left, right, cfg, max_disp):
        seen.append(max_disp)
        return sgm.copy(), 0.0

    monkeypatch.setattr(dense, "sgm_left", fake_sgm_left)
    result = CliRunner().invoke(pvm_main, ["densify", str(src), str(tmp_path / "dense"), "--method", "sgm",
                                           "--fill-confidence", "0.3"])
    assert result.exit_code == 0, result.output
    assert seen == [64, 64]  # the labeler's search range from the shards' config
    index = read_index(tmp_path / "dense")
    assert index.raw["densify"]["method"] == "sgm" and index.raw["densify"]["views"] == "left"
    filled = weighted_median(dense.fill_rows_nearest(sgm), records[0].left)
    with open_shard(index.shards[0][0]) as h5:
        for record in records:
            new = read_sample(h5, record.frame_id)
            labelled = np.isfinite(record.label)
            np.testing.assert_array_equal(new.label[labelled], record.label[labelled])
            want = np.where(filled[hole] > 0, filled[hole], np.nan)
            np.testing.assert_array_equal(new.label[hole], want)
            assert np.isnan(new.label[13, 20:26]).all() and np.isfinite(new.label[10:13, 20:26]).all()
            assert new.attrs["densify_filled_left"] == np.isfinite(want).sum() == 18
            np.testing.assert_allclose(new.confidence[hole][np.isfinite(want)], 0.3, atol=1e-3)
            np.testing.assert_array_equal(new.label_right, record.label_right)
            np.testing.assert_array_equal(new.left, record.left)


def test_sgm_method_with_both_views_fills_the_right_view_from_the_same_sgm_call(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    # A fake matcher answers both views at once (the right view's map >= 25, the left's < 10): the right view's
    # fills must be its own map through the median guided by the RIGHT image, from one call at the shards' range.
    import pvm_labeler.dense as dense
    from pvm_labeler.refine import weighted_median

    hole = (slice(10, 14), slice(20, 26))
    record, _ = _record("f0", hole)
    rng = np.random.default_rng(0)
    record.left = rng.integers(0, 255, record.left.shape, dtype=np.uint8)
    record.right = rng.integers(0, 255, record.right.shape, dtype=np.uint8)
    src = write_shard_dir(tmp_path / "src", [record], {"k": 6, "max_disp": 64})
    h, w = record.label.shape
    ramp = (5.0 + np.arange(w, dtype=np.float32) / 10)[None].repeat(h, 0)
    calls = []

    def fake_sgm_views(left, right, cfg, max_disp):
        calls.append(max_disp)
        return ramp.copy(), ramp + 20

    monkeypatch.setattr(dense, "sgm_views", fake_sgm_views)
    result = CliRunner().invoke(pvm_main, ["densify", str(src), str(tmp_path / "dense"), "--method", "sgm",
                                           "--fill-confidence", "0.3", "--views", "both"])
    assert result.exit_code == 0, result.output
    assert calls == [64]
    index = read_index(tmp_path / "dense")
    assert index.raw["densify"]["views"] == "both" and verify(tmp_path / "dense") == []
    want_left = weighted_median(ramp, record.left)
    want_right = weighted_median(ramp + 20, record.right)
    with open_shard(index.shards[0][0]) as h5:
        new = read_sample(h5, "f0")
    labelled = np.isfinite(record.label_right)
    np.testing.assert_array_equal(new.label[hole], want_left[hole])
    np.testing.assert_array_equal(new.label_right[hole], want_right[hole])
    np.testing.assert_array_equal(new.label_right[labelled], record.label_right[labelled])
    assert (new.label_right[hole] > 24).all()  # the right view's map (>= 25), not the left view's (< 10)
    np.testing.assert_allclose(new.confidence_right[hole], 0.3, atol=1e-3)
    assert (new.confidence_right[labelled] == 1).all()
    assert new.attrs["densify_filled_right"] == new.attrs["densify_filled_left"] == 24


def test_both_views_fills_equal_the_left_recipe_on_the_mirrored_pair() -> None:
    """The right view's fill from the shared cost volume is the left view's recipe (sgm_fill) run on the mirrored,
    swapped pair and mirrored back, and the left fill is sgm_fill itself: a layered scene with occlusions."""
    from pvm_labeler.common.datasets import discover, load_pair
    from pvm_labeler.config import LabelerConfig
    from pvm_labeler.densify import sgm_fill, sgm_fills_both

    sample = load_pair({r.frame_id: r for r in discover("sample", None)}["synthetic-001"])
    cfg = LabelerConfig(max_disp=sample.max_disp)
    fill_l, fill_r = sgm_fills_both(sample.left, sample.right, cfg)
    np.testing.assert_array_equal(fill_l, sgm_fill(sample.left, sample.right, cfg))
    mirrored = sgm_fill(np.ascontiguousarray(sample.right[:, ::-1]), np.ascontiguousarray(sample.left[:, ::-1]),
                        cfg)[:, ::-1]
    # the two cost-volume indexings can round a sub-pixel step differently on a handful of pixels
    differ = np.abs(fill_r - mirrored) > 0
    assert differ.mean() <= 1e-3 and np.abs(fill_r - mirrored).max() <= 0.25
    assert np.isfinite(fill_r).all()


def test_densify_refuses_an_unknown_method(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="method must be one of"):
        densify(tmp_path, tmp_path / "out", method="poisson")
    with pytest.raises(ValueError, match="views must be one of"):
        densify(tmp_path, tmp_path / "out", method="sgm", views="right")


def test_a_rewrite_into_another_jobs_folder_is_refused(tmp_path: Path) -> None:
    """densify / convert into a labeling run's folder replaced some of its shards and left the rest unindexed."""
    from pvm_labeler.common.errors import ShardError
    from pvm_labeler.shards import convert

    hole = (slice(10, 14), slice(20, 26))
    src = write_shard_dir(tmp_path / "src", [_record("f0", hole)[0]], {"k": 6})
    other = write_shard_dir(tmp_path / "other", [_record("g0", hole)[0], _record("g1", hole)[0]], {"k": 6})
    before = {p.name: p.read_bytes() for p in other.iterdir()}
    for run in (lambda: convert(src, other), lambda: densify(src, other, region_size=8, max_rms=0.1)):
        with pytest.raises(ShardError, match="holds shards that are no rewrite of"):
            run()
    assert {p.name: p.read_bytes() for p in other.iterdir()} == before
    out = convert(src, tmp_path / "copy")  # a rewrite of the same source may be redone there, e.g. with lzf
    assert convert(src, out, compression="gzip") == out and read_index(out).raw["compression"] == "gzip"
