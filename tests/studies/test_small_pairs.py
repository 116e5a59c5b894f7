"""S2's study (pipelines/studies/small_pairs.py): at factor 1 it scores exactly as ``optstereo-eval --valset``
(validation.score) does; its arms are written once and read back on a rerun."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import Echo, make_valset

from optstereo import validation
from optstereo.inference.config import InferenceConfig
from pipelines.studies import small_pairs


def echo() -> Echo:
    model = Echo()
    model.inference_config = InferenceConfig(adaptive_ref_pixels=4 * 32 * 64)
    return model


def test_factor_one_scores_as_the_valset_does(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    root = make_valset(tmp_path / "val", teacher_digest="not-this-model")
    monkeypatch.setattr(small_pairs, "load_model", lambda name: echo())
    got = small_pairs.score_small(1.0, root, factor=1.0)
    want = validation.score(echo(), validation.open_valset(root)).pairs
    assert [vars(p) for p in got] == [vars(p) for p in want]
    assert len(got) == 3 and all(p.pvm_n > 0 and p.teacher_n >= 0 for p in got)


def test_arms_are_written_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> None:
    calls = []

    def fake(cap: float, valset_dir: Path, factor: float) -> list[validation.PairScore]:
        calls.append(cap)
        return [validation.PairScore(f"p{i}", pvm_n=10, pvm_err=10.0 * cap + i, photo_sum=1.0, photo_n=1)
                for i in range(4)]

    monkeypatch.setattr(small_pairs, "score_small", fake)
    args = ["--valset", str(tmp_path), "--caps", "1", "1.25", "2", "--out", str(tmp_path / "out")]
    small_pairs.main(args)
    assert calls == [1.0, 1.25, 2.0]
    doc = json.loads((tmp_path / "out" / "small_f0.6_cap2.0.json").read_text())
    assert doc["summary"]["pvm_epe"] == pytest.approx((4 * 20.0 + 6) / 40)
    # against cap 1.25 (the first above 1): cap 2 adds 0.75 px on every pair, no spread, so no noise
    assert "cap 2.0: PVM EPE 2.1500" in capsys.readouterr().out
    small_pairs.main(args)
    assert calls == [1.0, 1.25, 2.0]  # read back, not scored again
