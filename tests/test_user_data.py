"""A user's own rig, end to end: label its left/right folders, fine-tune from a checkpoint (--init), evaluate with
the folder reader's options; evaluation streams frames (memory does not grow with their number)."""

from __future__ import annotations

import csv
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import TINY

from optstereo.checkpoint import export_safetensors, load_checkpoint
from optstereo.cli import eval_main, train_main
from optstereo.evaluate import evaluate_model
from optstereo.models import build_model
from pvm_labeler.cli import main as pvm_main
from pvm_labeler.common import io
from pvm_labeler.common.datasets import make_layered_scene

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _rig(root: Path, n: int, height: int = 64, width: int = 128) -> None:
    """cam0/, cam1/ image folders and disp/ GT (KITTI PNG x256), named as a rig would name them."""
    for name in ("cam0", "cam1", "disp"):
        (root / name).mkdir(parents=True, exist_ok=True)
    for i in range(n):
        scene = make_layered_scene(height, width, seed=i)
        io.write_image(root / "cam0" / f"{i:04d}.png", scene["left"])
        io.write_image(root / "cam1" / f"{i:04d}.png", scene["right"])
        io.write_kitti_disp(root / "disp" / f"{i:04d}.png", scene["gt"])


def test_label_finetune_evaluate_own_folders(tmp_path: Path) -> None:
    _rig(tmp_path / "rig", 2, 96, 192)
    runner = CliRunner()
    labels = tmp_path / "labels"
    result = runner.invoke(pvm_main, ["run", "--dataset", "folder", "--root", str(tmp_path / "rig"), "--left", "cam0",
                                      "--right", "cam1", "--gt", "disp", "--out", str(labels), "--k", "2",
                                      "--max-disp", "64", "--quiet"])
    assert result.exit_code == 0, result.output
    torch.manual_seed(0)
    base = export_safetensors(tmp_path / "base.safetensors", build_model("optstereo", iters=2, **TINY))
    result = runner.invoke(train_main, ["--labels", str(labels), "--out", str(tmp_path / "ft"), "--init", str(base),
                                        "--steps", "3", "--crop", "64x128", "--batch-size", "2", "--iters", "2",
                                        "--workers", "0", "--quiet"])
    assert result.exit_code == 0, result.output
    tuned = load_checkpoint(tmp_path / "ft")
    assert tuned.step == 3 and not torch.equal(tuned.model_state["disp_head.conv2.weight"],
                                               load_checkpoint(base).model_state["disp_head.conv2.weight"])
    result = runner.invoke(eval_main, ["--checkpoint", str(tmp_path / "ft"), "--dataset", "folder", "--root",
                                       str(tmp_path / "rig"), "--left", "cam0", "--right", "cam1", "--gt", "disp",
                                       "--out", str(tmp_path / "eval"), "--no-save-maps", "--quiet"])
    assert result.exit_code == 0, result.output
    rows = list(csv.DictReader(open(tmp_path / "eval" / "metrics.csv")))
    assert [r["frame_id"] for r in rows] == ["0000", "0001"]


def test_unknown_dataset_exits_2_naming_the_known_ones(tmp_path: Path) -> None:
    result = CliRunner().invoke(eval_main, ["--checkpoint", "x.pt", "--dataset", "kitty", "--out", str(tmp_path)])
    assert result.exit_code == 2 and "kitti15" in result.output and "kitti_unlabelled" in result.output


def test_evaluation_memory_does_not_grow_with_frames(tmp_path: Path) -> None:
    _rig(tmp_path / "rig", 200, 32, 64)
    torch.manual_seed(0)
    model = build_model("optstereo", iters=1, **TINY).eval()
    options = {"left": "cam0", "right": "cam1", "gt": "disp"}
    peaks = {}
    for limit in (20, 200):
        tracemalloc.start()
        result = evaluate_model(model, "folder", tmp_path / "rig", limit=limit, reader_options=options,
                                out_dir=tmp_path / f"eval{limit}")
        peaks[limit] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert result.summary["n_frames"] == limit and np.isfinite(result.summary["epe"])
    # 10x the frames; a list of frames would hold 200 x (2 images + GT + prediction) ~ 6 MB more
    assert peaks[200] < peaks[20] + 1_000_000, peaks


@pytest.mark.parametrize(("setting", "given", "ran"), [(None, None, 5), (2, None, 2), (2, 3, 3)])
def test_eval_summary_records_the_iterations_that_ran(tmp_path: Path, setting: int | None, given: int | None,
                                                      ran: int) -> None:
    # The summary's "iters" is the GRU iterations every pass ran: the caller's, else the file's settings, else the
    # network's default (it once recorded the caller's argument, None for a file whose settings said 3).
    from optstereo.inference.config import InferenceConfig

    _rig(tmp_path / "rig", 1)
    torch.manual_seed(0)
    model = build_model("optstereo", iters=5, **TINY).eval()
    model.inference_config = InferenceConfig(iters=setting)
    options = {"left": "cam0", "right": "cam1", "gt": "disp"}
    result = evaluate_model(model, "folder", tmp_path / "rig", iters=given, reader_options=options)
    assert result.summary["iters"] == ran
