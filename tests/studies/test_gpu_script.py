"""The one prepared device call of issue 49 (G4, ``pipelines/studies/gpu/teacher_all.sh``) run end to end on the CPU
at toy sizes: the same script and the same knobs as its registered call, only the device, sizes and step counts
changed (the header's "CPU smoke run"). A GPU window is rare and short; this keeps the script from rotting between
them."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from skimage.data import stereo_motorcycle

from optstereo.api import load_model, predict

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "pipelines" / "studies" / "gpu" / "teacher_all.sh"
#: G4's registered knobs (the header's one-call command), unchanged here.
G4 = {"NAME": "G4", "PART": "D", "TRAIN": "1", "SCHEDULE": "constant", "LR": "2e-5", "SNAPS": "3", "SPLIT": "2",
      "MISSING": "drop", "FILLS": "0", "SEED": "51"}
#: What the CPU changes: the device and the sizes.
SMOKE = {"DEVICE": "cpu", "AMP": "none", "BATCH": "1", "CROP": "64x128", "ITERS": "1", "PROBE": "2",
         "END_S": "100000", "STEPS_MAX": "6", "WORKERS": "0", "THREADS": "2", "JOBS": "2", "TEACHER_S": "600",
         "TEACHER": "pretrained", "INIT": "pretrained"}


def tiny_pack(root: Path, n: int = 3, width: int = 256) -> Path:
    """``n`` pairs of 96 x ``width`` crops of the embedded Middlebury motorcycle pair (shrunk 2x), as a pack's left/
    right/ folders. The labeler searches 192 px, so a pack narrower than that cannot be labelled."""
    left, right, _ = stereo_motorcycle()
    small = [cv2.resize(x, (x.shape[1] // 2, x.shape[0] // 2), interpolation=cv2.INTER_AREA) for x in (left, right)]
    for side in ("left", "right"):
        (root / side).mkdir(parents=True)
    for i in range(n):
        y, x = 20 * i, 30 * i
        for side, image in zip(("left", "right"), small, strict=True):
            cv2.imwrite(str(root / side / f"pair{i}.png"), np.ascontiguousarray(image[y:y + 96, x:x + width, ::-1]))
    return root


def run_script(pack: Path, tmp: Path) -> tuple[subprocess.CompletedProcess, Path]:
    """teacher_all.sh with G4's knobs and the CPU's sizes on ``pack``; (the finished process, its $OUT)."""
    out = tmp / "out"
    env = {**os.environ, **G4, **SMOKE, "PACK": str(pack), "WORK": str(tmp / "work"), "OUT": str(out),
           "PY": sys.executable}
    return subprocess.run(["bash", str(SCRIPT)], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600), out


@pytest.mark.skipif(sys.platform != "linux", reason="the device script is bash for the lent Linux machine")
def test_g4_call_runs_end_to_end_on_the_cpu(tmp_path: Path) -> None:
    pack = tiny_pack(tmp_path / "pack")
    done, out = run_script(pack, tmp_path)
    log = done.stdout + done.stderr
    assert done.returncode == 0, log[-3000:]
    assert "teacher maps: 3 pairs" in log and "3 samples in" in log, log[-3000:]
    assert "G4: 6 steps" in log and "G4: exit 0" in log and "fills not sent back (FILLS=0)" in log, log[-3000:]
    # SNAPS=3 over 6 steps: a snapshot every 2 steps, all three sent back as safetensors, nothing else large.
    snaps = sorted(out.glob("G4-*.safetensors"))
    assert [p.name for p in snaps] == ["G4-2.safetensors", "G4-4.safetensors", "G4-6.safetensors"]
    assert not list(out.glob("fills_*"))
    rows = [json.loads(line) for line in (out / "g4_metrics.jsonl").read_text().splitlines()]
    assert rows[-1]["step"] == 6 and rows[-1]["lr"] == pytest.approx(2e-5)  # SCHEDULE=constant keeps LR
    # A returned snapshot is what judge_chapter loads: a model giving a finite disparity of the pair's size.
    left = cv2.imread(str(pack / "left" / "pair0.png"))[..., ::-1].copy()
    right = cv2.imread(str(pack / "right" / "pair0.png"))[..., ::-1].copy()
    disp = predict(load_model(snaps[-1]), left, right)
    assert disp.shape == (96, 256) and np.isfinite(disp).all()


@pytest.mark.skipif(sys.platform != "linux", reason="the device script is bash for the lent Linux machine")
def test_g4_call_exits_non_zero_naming_the_stage_that_failed(tmp_path: Path) -> None:
    """Pairs narrower than the labeler's search: the labels fail, so nothing trains; the call must not read as a
    success (a device window's result is judged from its exit status and log), and the stages after the labels are
    skipped (they ran on nothing: a made-up 0.2 s/step probe, an empty merge, a failing training run)."""
    done, out = run_script(tiny_pack(tmp_path / "pack", width=160), tmp_path)
    log = done.stdout + done.stderr
    assert done.returncode != 0, log[-3000:]
    assert log.rstrip().endswith("FAILED: labels"), log[-3000:]  # the stages after it skipped, not run on nothing
    assert "fill, fills and training: skipped (the labels failed" in log and "probe:" not in log, log[-3000:]
    assert not list(out.glob("G4-*.safetensors"))
