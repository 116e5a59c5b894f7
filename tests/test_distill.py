"""optstereo.training.distill: the teacher's two views, their left-right check, the fills of PVM's holes, the CLI end
to end."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import TINY, make_shards

from optstereo.checkpoint import export_safetensors
from optstereo.inference.engine import infer
from optstereo.models import build_model
from optstereo.training import distill
from pvm_labeler.common.io import write_image
from pvm_labeler.shards import open_shard, read_index, read_sample
from pvm_labeler.voting import lr_check

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_consistent_views_equal_the_labelers_lr_check() -> None:
    """The vectorised check is the labeler's numba LRDCC on dense maps (its reference), NaNs and borders included."""
    rng = np.random.default_rng(0)
    left = rng.uniform(0, 12, (20, 40)).astype(np.float32)
    right = np.roll(left, -3, axis=1) + rng.normal(0, 0.8, left.shape).astype(np.float32)
    left[3, 5] = np.nan
    right[7, 30] = np.inf
    got_l, got_r = distill.consistent_views(left, right, 1.0)
    ref_l, ref_r = lr_check(left, right, 1.0)
    np.testing.assert_array_equal(got_l, ref_l)
    np.testing.assert_array_equal(got_r, ref_r)
    assert 0 < np.isfinite(got_l).mean() < 1  # the check keeps some pixels and drops others


def test_consistent_views_by_hand() -> None:
    """A 1 x 4 row: left pixel x reads the right view at floor(x - d + 0.5)."""
    left = np.array([[0.0, 1.0, 1.0, 3.0]], np.float32)
    right = np.array([[1.0, 1.0, 5.0, 0.0]], np.float32)
    out_l, out_r = distill.consistent_views(left, right, 0.5)
    # x=0 d=0 -> right[0]=1 (off by 1); x=1 d=1 -> right[0]=1 ok; x=2 d=1 -> right[1]=1 ok; x=3 d=3 -> right[0]=1 no
    np.testing.assert_array_equal(out_l, [[np.nan, 1.0, 1.0, np.nan]])
    # right x=0 d=1 -> left[1]=1 ok; x=1 d=1 -> left[2]=1 ok; x=2 d=5 -> off the image; x=3 d=0 -> left[3]=3 no
    np.testing.assert_array_equal(out_r, [[1.0, 1.0, np.nan, np.nan]])
    with pytest.raises(ValueError, match="one shape"):
        distill.consistent_views(left, right[:, :3])


class _Sample:
    def __init__(self, label: np.ndarray, label_right: np.ndarray, gt: np.ndarray | None = None) -> None:
        self.frame_id, self.label, self.label_right = "f", label, label_right
        self.confidence = np.where(np.isfinite(label), 0.9, 0.0).astype(np.float32)
        self.gt, self.gt_noc = gt, None


def test_fill_sample_keeps_labels_and_fills_only_consistent_holes(tmp_path: Path) -> None:
    teacher = np.full((2, 6), 2.0, np.float32)
    teacher_right = teacher.copy()
    teacher_right[1] = 7.0  # row 1 of the right view disagrees: no fill there in either view
    np.savez(distill.map_path(tmp_path, "f"), left=teacher, right=teacher_right)
    label = np.full((2, 6), np.nan, np.float32)
    label[0, 3] = 2.5  # a PVM label: kept as it is
    arrays, attrs = distill.fill_sample(_Sample(label, np.full((2, 6), np.nan, np.float32)), tmp_path, 0.5, 1.0)
    assert arrays["label"][0, 3] == 2.5 and arrays["confidence"][0, 3] == np.float16(0.9)
    filled = np.isfinite(arrays["label"]) & ~np.isfinite(label)
    # row 0: x >= 2 reads a consistent right view (x < 2 reads off the image); row 1: inconsistent
    np.testing.assert_array_equal(filled, [[False, False, True, False, True, True], [False] * 6])
    assert np.all(arrays["confidence"][filled] == np.float16(0.5))
    assert attrs == {"distill_filled_left": 3, "distill_filled_right": 4}
    with pytest.raises(ValueError, match="carries GT"):
        distill.fill_sample(_Sample(label, label, gt=teacher), tmp_path, 0.5, 1.0)
    with pytest.raises(ValueError, match="missing"):
        distill.read_teacher_maps(tmp_path, "other", (2, 6))
    with pytest.raises(ValueError, match="maps of other images"):
        distill.read_teacher_maps(tmp_path, "f", (3, 6))


def test_teacher_views_mirror_the_right_view() -> None:
    torch.manual_seed(0)
    model = build_model("optstereo", **TINY, iters=2).eval()
    rng = np.random.default_rng(1)
    left = rng.integers(0, 255, (32, 64, 3), dtype=np.uint8)
    right = np.roll(left, -3, axis=1)
    disp_left, disp_right = distill.teacher_views(model, left, right)
    np.testing.assert_array_equal(disp_left, infer(model, left, right))
    mirrored = infer(model, np.ascontiguousarray(right[:, ::-1]), np.ascontiguousarray(left[:, ::-1]))
    np.testing.assert_array_equal(disp_right, mirrored[:, ::-1])


def test_cli_maps_and_fill_end_to_end(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """maps over a folder of the shards' own images (resumable, on the engineered CPU pass), then fill: labels kept,
    holes filled, index says so."""
    shards = make_shards(tmp_path / "labels", n=2, with_gt=False)
    index = read_index(shards)
    folder = tmp_path / "pairs"
    samples = {}
    for path, ids in index.shards:
        with open_shard(path) as h5:
            for frame_id in ids:
                samples[frame_id] = read_sample(h5, frame_id)
                write_image(folder / "left" / f"{frame_id}.png", samples[frame_id].left)
                write_image(folder / "right" / f"{frame_id}.png", samples[frame_id].right)
    torch.manual_seed(0)
    teacher = tmp_path / "teacher.safetensors"
    export_safetensors(teacher, build_model("optstereo", **TINY, iters=1))
    import optstereo.cli.distill as distill_cli
    from optstereo.cli import distill_main as cli

    engineered, original = [], distill_cli.load_model
    monkeypatch.setattr(distill_cli, "load_model", lambda *a: engineered.append(original(*a)) or engineered[-1])
    maps = tmp_path / "maps"
    first = CliRunner().invoke(cli, ["maps", "--checkpoint", str(teacher), "--root", str(folder), "--out", str(maps)])
    assert first.exit_code == 0, first.output
    assert "2 new teacher maps" in first.output
    again = CliRunner().invoke(cli, ["maps", "--checkpoint", str(teacher), "--root", str(folder), "--out", str(maps)])
    assert "0 new teacher maps" in again.output  # resumed: nothing recomputed
    assert len(engineered) == 2 and all(type(m).__name__ == "EngineeredOptStereo" for m in engineered)
    # the CLI runs the engineered CPU pass (fastpath); its maps are the plain model's to float rounding
    from optstereo.checkpoint import build_model_from_checkpoint

    plain = build_model_from_checkpoint(teacher)
    for frame_id, sample in samples.items():
        with np.load(distill.map_path(maps, frame_id)) as data:
            for got, want in zip((data["left"], data["right"]), distill.teacher_views(plain, sample.left,
                                                                                      sample.right), strict=True):
                assert np.abs(got - want).mean() <= 0.01 and np.abs(got - want).max() <= 0.05
    for frame_id in samples:  # a random tiny teacher says nothing useful: known views, consistent where x >= 3
        with np.load(distill.map_path(maps, frame_id)) as data:
            assert data["left"].shape == samples[frame_id].label.shape
        np.savez(distill.map_path(maps, frame_id), left=np.full((32, 64), 3.0, np.float32),
                 right=np.full((32, 64), 3.0, np.float32))
    out = tmp_path / "filled"
    done = CliRunner().invoke(cli, ["fill", str(shards), str(maps), str(out)])
    assert done.exit_code == 0, done.output
    filled_index = read_index(out)
    assert filled_index.raw["distill"]["fill_confidence"] == distill.FILL_CONFIDENCE
    for path, ids in filled_index.shards:
        with open_shard(path) as h5:
            for frame_id in ids:
                new, old = read_sample(h5, frame_id), samples[frame_id]
                known = np.isfinite(old.label)
                np.testing.assert_array_equal(new.label[known], old.label[known])
                filled = np.isfinite(new.label) & ~known
                np.testing.assert_array_equal(np.flatnonzero(filled.any(axis=0)), [3])  # PVM's holes: x < 4
                assert np.all(new.label[filled] == 3.0) and filled[:, 3].all()
