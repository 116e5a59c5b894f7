"""J2's audit (pipelines/studies/judge_audit.py): the verdicts and rank correlations on hand-made rows, and the
models running with today's default settings."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from conftest import TINY

from optstereo.checkpoint import export_safetensors, model_inference
from optstereo.inference.config import InferenceConfig
from optstereo.models import build_model
from pipelines.studies import judge_audit


def row(pvm: float, teacher: float, photo: float, k15: float) -> dict:
    return {"val": {"pvm_bad3": pvm * 2, "pvm_epe": pvm, "teacher_bad3": teacher * 4, "teacher_epe": teacher,
                    "photometric": photo},
            "gt": {"kitti15": k15, "kitti12": k15 + 1, "middlebury": 20 - k15}}


def test_verdicts_by_hand() -> None:
    rows = {"v15": row(0.50, 0.90, 0.080, 7.3),
            "better_read_worse": row(0.52, 0.85, 0.081, 7.0),   # GT -0.3: PVM worse (disagrees), teacher agrees
            "worse_read_worse": row(0.55, 0.95, 0.082, 7.6),    # GT +0.3: every score agrees
            "same": row(0.40, 0.80, 0.070, 7.35),               # GT +0.05 < 0.1: no verdict
            "own": row(0.49, math.nan, 0.079, 7.1)}             # teacher missing: no verdict for it
    got = judge_audit.verdicts(rows)
    assert set(got) == {"better_read_worse", "worse_read_worse", "same", "own"}
    b = got["better_read_worse"]
    assert b["gt_says"] == "better" and b["kitti15_change"] == pytest.approx(-0.3)
    assert b["scores"]["pvm_epe"] == {"change": pytest.approx(0.02), "agrees": False}
    assert b["scores"]["teacher_epe"]["agrees"] is True and b["scores"]["photometric"]["agrees"] is False
    assert all(s["agrees"] is True for s in got["worse_read_worse"]["scores"].values())
    assert got["same"]["gt_says"] == "same" and all(s["agrees"] is None for s in got["same"]["scores"].values())
    assert got["own"]["scores"]["teacher_epe"]["agrees"] is None and got["own"]["scores"]["pvm_epe"]["agrees"] is True


def test_rank_agreement_skips_missing_scores() -> None:
    rows = {"a": row(0.1, 0.5, 0.07, 6.0), "b": row(0.2, math.nan, 0.08, 7.0), "c": row(0.3, 0.7, 0.06, 8.0),
            "d": row(0.4, 0.6, 0.09, 9.0)}
    got = judge_audit.rank_agreement(rows)
    assert got["pvm_epe"]["kitti15"] == {"rho": pytest.approx(1.0), "models": 4}
    assert got["pvm_epe"]["middlebury"]["rho"] == pytest.approx(-1.0)  # middlebury = 20 - k15 here
    # teacher over a, c, d: 0.5, 0.7, 0.6 against 6, 8, 9 -> ranks (0, 2, 1) vs (0, 1, 2): rho 0.5
    assert got["teacher_epe"]["kitti15"] == {"rho": pytest.approx(0.5), "models": 3}
    table = judge_audit.markdown(rows, got, judge_audit.verdicts(rows, base="a"))
    assert "| pvm_epe | 3 of 3 |" in table


def test_build_runs_a_file_with_todays_settings(tmp_path: Path) -> None:
    torch.manual_seed(0)
    model = build_model("optstereo", iters=5, **TINY)
    export_safetensors(tmp_path / "m.safetensors", model, inference=InferenceConfig(scale=0.5, iters=2))
    settings = judge_audit.shipped_settings()
    built = judge_audit.build("m.safetensors", tmp_path, settings)
    shipped = model_inference(judge_audit.build("pretrained", tmp_path, settings))
    assert model_inference(built) == shipped and shipped.iters == 3 and shipped.scale == 1.125
    assert torch.equal(next(built.parameters()), next(model.parameters()))


def test_plot_writes_a_png(tmp_path: Path) -> None:
    rows = {"v15": row(0.50, 0.90, 0.080, 7.3), "own": row(0.49, math.nan, 0.079, 7.1)}
    judge_audit.plot(rows, tmp_path / "audit.png")
    assert (tmp_path / "audit.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
