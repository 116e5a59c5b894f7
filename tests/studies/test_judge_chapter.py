"""G4's amended rule run mechanically (pipelines/studies/judge_chapter.py): stamping, the choice and the ship
verdict by hand, and the command end to end on tiny snapshots and a hand-made validation set."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import pytest
import torch
from conftest import TINY, make_valset

from optstereo.checkpoint import export_safetensors, model_inference
from optstereo.inference.config import InferenceConfig
from optstereo.models import build_model
from optstereo.validation import PairScore
from pipelines.studies import judge_chapter


def tiny_snapshot(path: Path, seed: int, config: InferenceConfig | None = None) -> Path:
    torch.manual_seed(seed)
    model = build_model("optstereo", iters=2, **TINY)
    return export_safetensors(path, model, inference=config or InferenceConfig(scale=0.5))


def doc(pvm: list[float], teacher: list[float]) -> dict:
    pairs = [asdict(PairScore(f"p{i}", pvm_n=1, pvm_err=a, teacher_n=1, teacher_err=b, photo_sum=1.0, photo_n=1))
             for i, (a, b) in enumerate(zip(pvm, teacher, strict=True))]
    return {"summary": {"pvm_epe": sum(pvm) / len(pvm)}, "pairs": pairs}


def test_stamp_gives_the_shipped_settings_and_keeps_the_weights(tmp_path: Path) -> None:
    snap = tiny_snapshot(tmp_path / "G4-7.safetensors", 0)
    out = judge_chapter.stamp(snap, tmp_path / "stamped", judge_chapter.shipped_settings())
    assert out == tmp_path / "stamped" / "G4-7.safetensors"
    got, before = judge_chapter.load_model(out, "cpu"), judge_chapter.load_model(snap, "cpu")
    assert model_inference(got) == model_inference(judge_chapter.load_model("pretrained", "cpu"))
    assert all(torch.equal(a, b) for a, b in zip(got.state_dict().values(), before.state_dict().values(), strict=True))


def test_decide_takes_the_lowest_pvm_epe_and_guards_with_the_teacher() -> None:
    base = doc([0.50, 0.52, 0.54, 0.56], [0.9, 1.0, 1.1, 1.2])
    lower = doc([0.48, 0.50, 0.52, 0.54], [0.9, 1.0, 1.1, 1.2])  # -0.02 on each pair, teacher unchanged
    lowest_off_teacher = doc([0.47, 0.49, 0.51, 0.53], [1.0, 1.1, 1.2, 1.3])  # lower still, teacher +0.1
    assert judge_chapter.decide(base, {"a": lower})[0] == "a"
    chosen, why = judge_chapter.decide(base, {"a": lower, "b": lowest_off_teacher})
    assert chosen is None and why.startswith("b (lowest PVM EPE of 2): not a candidate")  # no second pick


def test_ships_by_hand() -> None:
    assert judge_chapter.ships({"kitti15": 7.20, "kitti12": 9.15, "middlebury": 12.10})[0]
    assert not judge_chapter.ships({"kitti15": 7.27, "kitti12": 8.0, "middlebury": 11.0})[0]  # not below 7.27
    ok, line = judge_chapter.ships({"kitti15": 7.0, "kitti12": 9.2, "middlebury": 11.0})
    assert not ok and line.startswith("does not ship: kitti15 7.00 (< 7.27), kitti12 9.20 (<= 9.15)")


def test_command_end_to_end(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # the default is replaced by a tiny model too (a shipped-size pass on the hand-made set is not needed here)
    shipped = tiny_snapshot(tmp_path / "v15.safetensors", 9, InferenceConfig(iters=1))  # its settings are stamped
    real_load = judge_chapter.load_model
    monkeypatch.setattr(judge_chapter, "load_model",
                        lambda spec, device="cpu": real_load(shipped if spec == "pretrained" else spec, device))
    val = make_valset(tmp_path / "val", teacher_digest="nobody")
    snaps = [tiny_snapshot(tmp_path / f"G4-{i}.safetensors", i) for i in (1, 2)]
    judge_chapter.main([*map(str, snaps), "--valset", str(val), "--out", str(tmp_path / "out")])
    verdict = (tmp_path / "out" / "verdict.txt").read_text()
    assert "(lowest PVM EPE of 2)" in verdict and "teacher EPE" in verdict
    assert {p.name for p in (tmp_path / "out").glob("*.gtfree.json")} == {"v15.gtfree.json", "G4-1.gtfree.json",
                                                                         "G4-2.gtfree.json"}
    assert not (tmp_path / "out" / "gt.json").exists()  # no --gt
