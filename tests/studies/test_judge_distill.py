"""D3-D5's rule run mechanically (pipelines/studies/judge_distill.py): which checkpoint is judged, the verdict by
hand, and the command end to end on a tiny run's checkpoints and a hand-made validation set."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import pytest
import torch
from conftest import TINY, make_shards, make_valset, tiny_config

from optstereo.checkpoint import export_safetensors, model_inference
from optstereo.inference.config import InferenceConfig
from optstereo.models import build_model
from optstereo.training.loop import main as train
from optstereo.validation import PairScore
from pipelines.studies import judge_chapter, judge_distill


def doc(pvm: list[float], teacher: list[float]) -> dict:
    pairs = [asdict(PairScore(f"p{i}", pvm_n=1, pvm_err=a, teacher_n=1, teacher_err=b, photo_sum=1.0, photo_n=1))
             for i, (a, b) in enumerate(zip(pvm, teacher, strict=True))]
    return {"summary": {"pvm_epe": sum(pvm) / len(pvm), "teacher_epe": sum(teacher) / len(teacher)}, "pairs": pairs}


def test_pick_the_last_or_the_lowest_teacher_epe() -> None:
    scores = {"ckpt-0000400": doc([0.5], [0.8]), "ckpt-0001200": doc([0.5], [0.9]), "ckpt-0000800": doc([0.5], [0.7])}
    assert judge_distill.pick(scores, "last") == "ckpt-0001200"
    assert judge_distill.pick(scores, "lowest-teacher") == "ckpt-0000800"
    with pytest.raises(ValueError, match="last or lowest-teacher"):
        judge_distill.pick(scores, "best")


def test_decide_by_hand() -> None:
    """Teacher EPE -0.1 on each of 4 pairs but one (-0.1, -0.1, -0.1, 0): mean -0.075, 2 SE = 2 * 0.05 / 2 = 0.05
    -> a candidate while the pooled PVM EPE rises by at most 0.02; +0.03 -> not one."""
    base = doc([0.50, 0.52, 0.54, 0.56], [0.9, 1.0, 1.1, 1.2])
    closer = doc([0.51, 0.53, 0.55, 0.57], [0.8, 0.9, 1.0, 1.2])  # PVM EPE +0.01
    ok, line = judge_distill.decide(base, closer, "c", "the last of 1")
    assert ok and line.startswith("c (the last of 1): teacher EPE change -0.0750 (2 SE 0.0500), pooled PVM EPE "
                                  "+0.0100") and line.endswith("CANDIDATE")
    drifted = doc([0.53, 0.55, 0.57, 0.59], [0.8, 0.9, 1.0, 1.2])  # PVM EPE +0.03: over the bound
    assert not judge_distill.decide(base, drifted, "d", "x")[0]
    unchanged = doc([0.50, 0.52, 0.54, 0.56], [0.9, 1.0, 1.1, 1.2])
    assert judge_distill.decide(base, unchanged, "u", "x")[1].endswith("not a candidate")


def test_command_end_to_end(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    shipped = tmp_path / "v15.safetensors"  # the default replaced by a tiny model: its settings are stamped
    torch.manual_seed(9)
    export_safetensors(shipped, build_model("optstereo", iters=1, **TINY), inference=InferenceConfig(iters=1))
    real_load = judge_chapter.load_model
    monkeypatch.setattr(judge_chapter, "load_model",
                        lambda spec, device="cpu": real_load(shipped if spec == "pretrained" else spec, device))
    labels = make_shards(tmp_path / "labels", n=4, with_gt=False)
    train(tiny_config(labels, tmp_path / "run", steps=4, ckpt_every=2, keep_ckpts=10), progress=False)
    val = make_valset(tmp_path / "val", teacher_digest="nobody")
    judge_distill.main([str(tmp_path / "run"), "--valset", str(val), "--out", str(tmp_path / "out"), "--pick", "last"])
    verdict = (tmp_path / "out" / "verdict.txt").read_text()
    assert verdict.startswith("ckpt-0000004 (the last of 2): teacher EPE change") and "PVM EPE" in verdict
    assert {p.name for p in (tmp_path / "out").glob("*.gtfree.json")} == {"v15.gtfree.json", "ckpt-0000002.gtfree.json",
                                                                         "ckpt-0000004.gtfree.json"}
    stamped = real_load(tmp_path / "out" / "stamped" / "ckpt-0000004.safetensors", "cpu")
    assert model_inference(stamped) == InferenceConfig(iters=1)  # the shipped settings, stamped
    assert not (tmp_path / "out" / "gt.json").exists()  # no --gt
    with pytest.raises(SystemExit, match="no ckpt-"):
        judge_distill.main([str(tmp_path / "labels"), "--valset", str(val), "--out", str(tmp_path / "o2"),
                            "--pick", "last"])
