"""Peak memory of the long-running programs does not grow with the number of frames.

``optstereo-eval`` over 50 and 500 frames, ``pvm-label run`` and ``optstereo-train`` over 20 and 200 frames, each a
subprocess that prints its own peak RSS (VmHWM, ``pvm_labeler.parallel.peak_rss_mb``: a fresh process's, never its
parent's) when it exits. The frames are tiny (32x64; the trainer's 64x128), so one frame's arrays are small: a
program that kept them would grow by

    eval:  pred + gt (float32) + left (uint8 RGB) = 22 KiB a frame -> 9.7 MiB over the 450 extra frames;
    label: left + right (uint8 RGB) + label + label_right + confidence + gt (float32) = 44 KiB a frame
           -> 7.7 MiB over the 180 extra frames.

The bounds sit below those (half of the per-frame leak), and above what the runs keep per frame by design: a
row of metrics per frame in the evaluator (~1.5 KiB), a shard entry per frame in the labeler's index. Measured on a
2-core x86 box: eval 324.7 -> 325.8 MiB, label 240.3 -> 241.2 MiB.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import TINY, make_folder, make_shards

from optstereo.checkpoint import save_checkpoint
from pvm_labeler.shards import read_index

pytestmark = [pytest.mark.slow, pytest.mark.faults,
              pytest.mark.skipif(not sys.platform.startswith("linux"), reason="VmHWM is Linux-only")]

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1", "CUDA_VISIBLE_DEVICES": ""}
#: Runs ``{module}.{function}()`` as its console script would, printing the process's peak RSS when it exits.
WRAPPER = ("import atexit, sys; from pvm_labeler.parallel import peak_rss_mb; "
           "atexit.register(lambda: print(f'PEAK_RSS_MB {{peak_rss_mb():.2f}}', file=sys.stderr)); "
           "from {module} import {function}; sys.argv[0] = '{function}'; {function}()")
EVAL_GROWTH_MIB = 5.0  # 50 -> 500 frames; a kept frame would add 9.7 MiB
LABEL_GROWTH_MIB = 4.0  # 20 -> 200 frames; a kept frame would add 7.7 MiB


def _peak_mib(module: str, function: str, *args: str) -> float:
    cmd = [sys.executable, "-c", WRAPPER.format(module=module, function=function), *args]
    result = subprocess.run(cmd, cwd=REPO, env=ENV, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    found = re.findall(r"PEAK_RSS_MB ([0-9.]+)", result.stderr)
    assert found, result.stderr[-2000:]
    return float(found[-1])


@pytest.fixture(scope="module")
def frames(tmp_path_factory: pytest.TempPathFactory) -> dict[int, Path]:
    """Folder datasets (left/, right/, gt/) of 2, 20, 50, 200 and 500 tiny 32x64 pairs with GT."""
    base = tmp_path_factory.mktemp("frames")
    return {n: make_folder(base / f"n{n}", n=n, size=(32, 64)) for n in (2, 20, 50, 200, 500)}


def test_eval_peak_rss_does_not_grow_with_frames(frames: dict[int, Path], tmp_path: Path) -> None:
    torch.manual_seed(0)
    from optstereo.models import build_model

    ckpt = save_checkpoint(tmp_path / "tiny.pt", model=build_model("optstereo", **TINY), step=0)

    def peak(n: int) -> float:
        return _peak_mib("optstereo.cli", "eval_main", "--checkpoint", str(ckpt), "--dataset", "folder", "--root",
                         str(frames[n]), "--out", str(tmp_path / f"eval{n}"), "--device", "cpu", "--quiet")

    small, large = peak(50), peak(500)
    assert len((tmp_path / "eval500" / "metrics.csv").read_text().splitlines()) == 501  # header + every frame
    assert large - small < EVAL_GROWTH_MIB, f"peak RSS {small:.1f} MiB at 50 frames, {large:.1f} MiB at 500"


def test_label_peak_rss_does_not_grow_with_frames(frames: dict[int, Path], tmp_path: Path) -> None:
    def peak(n: int) -> float:
        return _peak_mib("pvm_labeler.cli", "main", "run", "--dataset", "folder", "--root", str(frames[n]), "--out",
                         str(tmp_path / f"labels{n}"), "--k", "2", "--max-disp", "16", "--jobs", "1", "--quiet")

    peak(2)  # warm numba's on-disk cache: a compiling run peaks ~120 MiB higher and would hide a leak after it
    small, large = peak(20), peak(200)
    assert read_index(tmp_path / "labels200").num_samples == 200
    assert large - small < LABEL_GROWTH_MIB, f"peak RSS {small:.1f} MiB at 20 frames, {large:.1f} MiB at 200"


#: 20 -> 200 frames of 64x128: a kept frame (left + right uint8 RGB, label + label_right + confidence float32,
#: 144 KiB) would add 25 MiB over the 180 extra frames; the stream keeps a shuffle buffer of 8 samples by design.
TRAIN_GROWTH_MIB = 6.0


def test_train_peak_rss_does_not_grow_with_shards(tmp_path: Path) -> None:
    """optstereo-train streams the shards: the same 100 steps (batch 2, so every frame of the large set is read
    at least once) peak at the same RSS over 20 and over 200 frames (ten times the shards)."""

    def peak(n: int) -> float:
        labels = make_shards(tmp_path / f"shards{n}", n=n, shard_size=2, height=64, width=128)
        model = [f"--set=model.{k}={v}" for k, v in TINY.items()]
        return _peak_mib("optstereo.cli", "train_main", "--labels", str(labels), "--out", str(tmp_path / f"run{n}"),
                         "--steps", "100", "--batch-size", "2", "--crop", "32x64", "--iters", "1", "--workers", "0",
                         "--threads", "1", "--device", "cpu", "--ckpt-every", "1000", "--log-every", "50",
                         "--set", "data.shuffle_buffer=8", "--set", "tensorboard=false", "--quiet", *model)

    small, large = peak(20), peak(200)
    assert (tmp_path / "run200" / "last.pt").exists()
    assert large - small < TRAIN_GROWTH_MIB, f"peak RSS {small:.1f} MiB at 20 frames, {large:.1f} MiB at 200"
