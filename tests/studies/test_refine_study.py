"""pipelines.studies.refine_study's choice of settings without GT, on a hand-made frame whose labels are the truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipelines.studies import refine_study
from pvm_labeler.refine import MedianParams


def test_choose_picks_the_setting_that_restores_the_labels(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    # A dark/bright step (disparity 30 | 5 px at column 20) whose prediction is an 8-px ramp across the edge: every
    # ramp pixel more than 3 px off is bad-3 against the labels. Radius 1 cannot undo an 8-px ramp, radius 6 can.
    image = np.full((16, 40, 3), 30, np.uint8)
    image[:, 20:] = 220
    truth = np.broadcast_to(np.where(np.arange(40) < 20, 30.0, 5.0).astype(np.float32), (16, 40)).copy()
    pred = truth.copy()
    pred[:, 16:24] = np.linspace(30, 5, 8, dtype=np.float32)
    (tmp_path / "preds" / "kitti_unlabelled").mkdir(parents=True)
    np.save(tmp_path / "preds" / "kitti_unlabelled" / "f0.npy", pred)
    monkeypatch.setattr(refine_study, "PREDS", tmp_path / "preds")
    monkeypatch.setattr(refine_study, "RESULTS", tmp_path / "results")
    monkeypatch.setattr(refine_study, "GRID", (MedianParams(1, 20.0), MedianParams(6, 20.0)))
    monkeypatch.setattr(refine_study, "label_samples", lambda every=3: iter([("f0", image, truth)]))
    doc = refine_study.step_choose()
    assert doc["chosen"] == "r6_s20"
    assert doc["rows"]["r6_s20"]["bad3"] == 0.0 < doc["rows"]["r1_s20"]["bad3"] <= doc["rows"]["none"]["bad3"]
    assert (tmp_path / "results" / "choose.md").read_text().endswith("chosen (lowest bad-3): r6_s20\n")
