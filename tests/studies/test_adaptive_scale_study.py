"""pipelines.studies.adaptive_scale: the shipped model's adaptive-scale constants from real unlabelled pairs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import TINY
from safetensors.torch import load_file

import pipelines.studies.adaptive_scale as adaptive
import pvm_labeler.common.datasets as datasets
from optstereo.api import load_model
from optstereo.checkpoint import export_safetensors
from optstereo.inference.config import InferenceConfig
from optstereo.inference.engine import infer
from optstereo.models import build_model

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_pipeline_reference_and_candidate(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, shared_data: Path) -> None:
    # pipelines.studies.adaptive_scale on two real unlabelled pairs with a tiny network: the constants are the medians
    # of each pair's 95th percentile (recomputed here from infer) and pixel count; the candidate keeps the weights
    # byte for byte and records the constants.
    torch.manual_seed(0)
    source = export_safetensors(tmp_path / "m.safetensors", build_model("optstereo", **TINY, iters=2),
                                inference=InferenceConfig(scale=0.5))
    pairs = datasets.discover("kitti_unlabelled", shared_data / "kitti_unlabelled")[:2]
    monkeypatch.setattr(datasets, "discover", lambda *args, **kwargs: pairs)
    doc = adaptive.step_reference(str(source), tmp_path / "ref.json")
    model = load_model(source)
    p95 = []
    for ref in pairs:
        sample = datasets.load_pair(ref)
        p95.append(np.percentile(infer(model, sample.left, sample.right, scale=0.5, refine="none"), 95))
    assert [f["p95"] for f in doc["frames"]] == pytest.approx(p95, rel=1e-5)
    assert doc["scale_ref_disp"] == round(float(np.median(p95)), 1)
    assert doc["scale_ref_pixels"] == int(np.median([f["height"] * f["width"] for f in doc["frames"]]))
    assert doc["input_scale"] == 0.5

    monkeypatch.setattr(adaptive, "CANDIDATE", tmp_path / "candidate.safetensors")
    out = adaptive.step_candidate(str(source), tmp_path / "ref.json")
    own = load_model(out).inference_config
    assert (own.adaptive_ref_disp, own.adaptive_ref_pixels) == (doc["scale_ref_disp"], doc["scale_ref_pixels"])
    before, after = load_file(source), load_file(out)
    assert before.keys() == after.keys() and all(torch.equal(before[k], after[k]) for k in before)
