"""The lent-GPU kit of pipelines/studies: the JPEG carry pack, and gpu/continue.sh end to end at toy size on the CPU."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import torch
from conftest import TINY, make_synthetic_pair

from optstereo.checkpoint import export_safetensors, load_checkpoint
from optstereo.models import build_model
from pipelines.studies.carry_pack import write_jpeg_folder
from pvm_labeler.common.datasets import discover, load_pair


# -- the carry pack -------------------------------------------------------------------------------------------------
def test_jpeg_folder_pack(tmp_path: Path) -> None:
    smooth = np.add.outer(np.arange(32), np.arange(48)).astype(np.uint8)[..., None].repeat(3, axis=2) * 2
    for i in range(2):
        for view in ("image_2", "image_3"):
            (tmp_path / "src" / view).mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(tmp_path / "src" / view / f"{i:06d}_10.png"), smooth + i)
    n = write_jpeg_folder("kitti_unlabelled", tmp_path / "src", tmp_path / "pack", quality=95)
    assert n == 2
    refs = discover("folder", tmp_path / "pack")
    assert [r.frame_id for r in refs] == ["000000_10", "000001_10"]
    original = load_pair(discover("kitti_unlabelled", tmp_path / "src")[0]).left.astype(float)
    packed = load_pair(refs[0]).left.astype(float)
    assert packed.shape == original.shape and np.abs(packed - original).mean() < 2  # lossy, but the same image


def test_gpu_continue_script_runs_on_cpu(tmp_path: Path, rng: np.random.Generator) -> None:
    """gpu/continue.sh end to end at toy size on the CPU: label, probe, size, train from the head, export."""
    repo = Path(__file__).resolve().parents[2]
    for i in range(2):
        left, right = make_synthetic_pair(rng, height=96, width=256, disp=6)
        for view, img in (("left", left), ("right", right)):
            (tmp_path / "pack" / view).mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(tmp_path / "pack" / view / f"{i:06d}.png"), img)
    torch.manual_seed(0)
    init = export_safetensors(tmp_path / "head.safetensors", build_model("optstereo", **TINY))  # a stand-in head
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "DEVICE": "cpu", "AMP": "none", "BATCH": "1",
           "CROP": "64x128", "ITERS": "1", "BUDGET_S": "1", "PROBE": "4", "WORKERS": "1", "THREADS": "1", "JOBS": "1",
           "PACK": str(tmp_path / "pack"), "WORK": str(tmp_path / "work"), "OUT": str(tmp_path / "out"),
           "PY": sys.executable, "NAME": "toy", "INIT": str(init)}
    proc = subprocess.run(["bash", "pipelines/studies/gpu/continue.sh"], cwd=repo, env=env, capture_output=True,
                          text=True)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "-> 4 steps" in proc.stdout  # 1 s of budget rounds down to nothing: the floor of 4 steps
    out = load_checkpoint(tmp_path / "out" / "toy.safetensors")
    start = load_checkpoint(init)
    # the run's --max-minutes is BUDGET_S too (1 s): on a busy machine it may stop before the 4 sized steps
    assert 1 <= out.step <= 4 and out.model_config["feature_dim"] == start.model_config["feature_dim"]
    assert out.inference_config.scale == 1.625  # the default U(1.5, 1.75): the export runs at its middle
    moved = [k for k in start.model_state if not torch.equal(start.model_state[k], out.model_state[k])]
    assert moved, "the weights should have moved from the head"
    config = (tmp_path / "out" / "config.yaml").read_text()
    assert "lambda_t: 0.0" in config and "conf_weight: true" in config
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["config.yaml", "env.txt", "metrics.jsonl",
                                                                     "toy.safetensors"]
