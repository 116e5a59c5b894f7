"""pipelines.studies.cascade_select: the GT-free check and the jump-limit calibration on real unlabelled pairs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import TINY

import pipelines.studies.cascade_select as check
import pvm_labeler.common.datasets as datasets
from optstereo.api import load_model
from optstereo.checkpoint import export_safetensors
from optstereo.inference.config import InferenceConfig
from optstereo.inference.engine import infer
from optstereo.models import build_model
from pvm_labeler.common.metrics import MetricAccumulator
from pvm_labeler.shards import ShardRecord, write_shard_dir

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_pipeline_check_on_real_pairs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, shared_data: Path) -> None:
    # pipelines.studies.cascade_select on two real unlabelled pairs (cropped) with a tiny cascade network: its zero and
    # coarse answers are infer's with the start off and on, each scored against the shard's labels
    torch.manual_seed(0)
    source = export_safetensors(tmp_path / "m.safetensors",
                                build_model("optstereo", **{**TINY, "iters": 2}),
                                inference=InferenceConfig(coarse_start=True))
    records = []
    for ref in datasets.discover("kitti_unlabelled", shared_data / "kitti_unlabelled")[:2]:
        pair = datasets.load_pair(ref)
        # 136 wide: the coarse start's half-size pair (68 -> 64 columns) keeps the 64 that 4 cost levels need
        left, right = pair.left[-64:, 300:436].copy(), pair.right[-64:, 300:436].copy()
        label = np.full(left.shape[:2], 2.0, np.float32)
        label[:, :20] = np.nan
        records.append(ShardRecord(frame_id=ref.frame_id, left=left, right=right, label=label,
                                   label_right=label.copy(), confidence=np.ones(left.shape[:2], np.float32),
                                   attrs={"sources": {}, "eps": np.zeros(1), "factors": np.ones(1), "seed": 0}))
    labels = write_shard_dir(tmp_path / "labels", records)
    monkeypatch.setattr(check, "LABELS", labels)
    monkeypatch.setattr(check, "RESULTS", tmp_path / "results")
    doc = check.step_check(str(source), every=1)
    model = load_model(source)
    for rec, row in zip(records, doc["frames"], strict=True):
        model.inference_config = InferenceConfig(coarse_start=True)
        coarse = infer(model, rec.left, rec.right, scale=1.0, refine="none")
        model.inference_config = InferenceConfig()
        zero = infer(model, rec.left, rec.right, scale=1.0, refine="none")
        for name, disp in (("zero", zero), ("coarse", coarse)):
            assert row[name]["epe"] == pytest.approx(MetricAccumulator().update(disp, rec.label)["epe"], rel=1e-5)
    assert (tmp_path / "results" / "check.json").exists() and doc["select"]["n_valid"] == 2 * 64 * 116
    # calibrate: with no limit its choice is the check's; the chosen limit is the grid's lowest bad-3, ties tighter
    cal = check.step_calibrate(str(source), "tiny", every=1, grid=(0.0, 0.05, 0.2))
    assert cal["grid"]["0.0"]["epe"] == pytest.approx(doc["select"]["epe"], rel=1e-6)
    best = min(row["bad3"] for row in cal["grid"].values())
    assert cal["grid"][repr(cal["jump"])]["bad3"] == best
    assert cal["jump"] == min((j for j in (0.05, 0.2, 0.0) if cal["grid"][repr(j)]["bad3"] == best),
                              key=lambda j: j if j > 0 else float("inf"))
    assert (tmp_path / "results" / "calibrate_tiny.json").exists()
