"""optstereo.adapt: the held-back tiles by hand, the guard, and the whole command end to end on a tiny folder with a
tiny model (labels, hold-back, fine-tuning, report, checkpoint)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import TINY

from optstereo.adapt import AdaptConfig, guard, right_mask, tile_mask
from optstereo.checkpoint import save_checkpoint
from optstereo.models import build_model
from pvm_labeler.common.datasets import make_layered_scene
from pvm_labeler.common.io import write_image, write_pfm

pytestmark = pytest.mark.usefixtures("one_torch_thread")

def test_tile_mask_holds_back_whole_tiles() -> None:
    mask = tile_mask((10, 13), 0.5, 4, np.random.default_rng(0))
    assert mask.shape == (10, 13)
    tiles = mask[::4, ::4]  # 3 x 4 tiles, the last ones cut by the frame
    np.testing.assert_array_equal(mask, np.repeat(np.repeat(tiles, 4, 0), 4, 1)[:10, :13])
    assert 0 < tiles.sum() < tiles.size
    for fraction in (1e-9, 1 - 1e-9):  # never all or nothing
        tiles = tile_mask((8, 8), fraction, 4, np.random.default_rng(1))[::4, ::4]
        assert 0 < tiles.sum() < tiles.size


def test_right_mask_follows_the_right_labels() -> None:
    held = np.zeros((1, 6), bool)
    held[0, 4] = True
    label_right = np.array([[4.0, 2.0, 3.0, np.nan, 1.0, 9.0]], np.float32)
    # right x matches left x + d: 0 -> 4 (held), 1 -> 3, 2 -> 5, 3 none, 4 -> 5, 5 -> 14 outside
    np.testing.assert_array_equal(right_mask(held, label_right), [[True, False, False, False, False, False]])


def test_guard() -> None:
    # 8 bad pixels of 1000 before: up to 8 + 2 sqrt(9) = 14 allowed after, with EPE not higher
    before = {"held_epe": 1.0, "held_bad3": 0.8, "held_pixels": 1000}
    assert guard(before, {"held_epe": 0.9, "held_bad3": 0.8, "held_pixels": 1000})
    assert guard(before, {"held_epe": 1.0, "held_bad3": 1.4, "held_pixels": 1000})
    assert not guard(before, {"held_epe": 0.9, "held_bad3": 1.5, "held_pixels": 1000})
    assert not guard(before, {"held_epe": 1.01, "held_bad3": 0.0, "held_pixels": 1000})
    with pytest.raises(ValueError, match="--holdout"):
        AdaptConfig(dataset="folder", root=None, out=Path("x"), holdout=1.0).check()


def _rig(root: Path, n: int = 2) -> None:
    for i in range(n):
        scene = make_layered_scene(96, 160, seed=i)
        for side, image in (("cam0", scene["left"]), ("cam1", scene["right"])):
            (root / side).mkdir(parents=True, exist_ok=True)
            write_image(root / side / f"{i:03d}.png", image)
        (root / "gt").mkdir(exist_ok=True)
        write_pfm(root / "gt" / f"{i:03d}.pfm", np.nan_to_num(scene["gt"], nan=np.inf))


@pytest.mark.slow
def test_adapt_end_to_end(tmp_path: Path) -> None:
    from optstereo.cli import adapt_main

    _rig(tmp_path / "rig")
    torch.manual_seed(0)
    ckpt = save_checkpoint(tmp_path / "tiny.pt", model=build_model("optstereo", **TINY), step=0)
    out = tmp_path / "adapt"
    args = ["--root", str(tmp_path / "rig"), "--left", "cam0", "--right", "cam1", "--gt", "gt", "--out", str(out),
            "--init", str(ckpt), "--steps", "3", "--device", "cpu", "--quiet", "--max-disp", "64"]
    res = CliRunner().invoke(adapt_main, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    report = json.loads((out / "report.json").read_text())
    assert report["pairs"] == 2 and report["config"]["steps"] == 3
    for side in ("before", "after"):
        assert report[side]["held_pixels"] > 0 and np.isfinite(report[side]["held_epe"])
        assert "gt_bad3" in report[side]  # the folder has GT: scored, never trained on
    assert report["adapted"] == guard(report["before"], report["after"])
    assert Path(report["checkpoint"]).is_file() and (out / "report.md").is_file()
    assert (out / "run" / "last.pt").is_file() and (out / "holdout.npz").is_file()
    # the training shards hold no GT and none of the held-back labels
    from pvm_labeler.shards import open_shard, read_index, read_sample

    masks = np.load(out / "holdout.npz")
    for path, ids in read_index(out / "train_labels").shards:
        with open_shard(path) as h5:
            for frame_id in ids:
                sample = read_sample(h5, frame_id)
                assert sample.gt is None and np.all(np.isnan(sample.label[masks[frame_id]]))
    # a second call resumes: labels and training are done, the report is written again
    res = CliRunner().invoke(adapt_main, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
