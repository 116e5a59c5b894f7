"""The registered rules of ``pipelines.studies.long_run`` on hand-made validation results."""

from __future__ import annotations

from dataclasses import asdict

import pytest

from optstereo.validation import PairScore
from pipelines.studies.long_run import candidate, non_inferior


def _doc(pvm_epe: float, teacher_epe: float, photos: list[float]) -> dict:
    pairs = [asdict(PairScore(frame_id=f"p{i}", photo_sum=v, photo_n=1)) for i, v in enumerate(photos)]
    return {"summary": {"pvm_epe": pvm_epe, "teacher_epe": teacher_epe}, "pairs": pairs}


def test_non_inferior_by_hand() -> None:
    base = _doc(0.519, 0.888, [0.10, 0.20, 0.30, 0.40])
    # photometric per-pair changes +0.001, -0.001, +0.001, -0.001: mean 0, noise 2 * 0.001155 / 2 = 0.001155
    level = _doc(0.523, 0.900, [0.101, 0.199, 0.301, 0.399])
    ok, why = non_inferior(base, level)
    assert ok and why.startswith("not worse: pooled PVM EPE +0.0040 px")
    assert not non_inferior(base, _doc(0.5244, 0.900, [0.101, 0.199, 0.301, 0.399]))[0]  # E5: +0.0054 > 0.005
    assert not non_inferior(base, _doc(0.519, 0.909, [0.101, 0.199, 0.301, 0.399]))[0]  # teacher +0.021
    worse_photo = _doc(0.519, 0.888, [0.103, 0.202, 0.303, 0.402])  # +0.0025 mean, noise 0.001
    ok, why = non_inferior(base, worse_photo)
    assert not ok and "photometric +0.0025" in why


def test_non_inferior_for_the_teacher_itself() -> None:
    """The teacher scored against its own maps has no teacher column (NaN on both sides): judged without it (Q2); a
    NaN on one side only is still a failure."""
    nan = float("nan")
    base = _doc(0.417, nan, [0.10, 0.20, 0.30, 0.40])
    ok, why = non_inferior(base, _doc(0.4172, nan, [0.101, 0.199, 0.301, 0.399]))
    assert ok and "teacher EPE not scored" in why
    assert not non_inferior(base, _doc(0.423, nan, [0.101, 0.199, 0.301, 0.399]))[0]  # PVM EPE +0.006
    assert not non_inferior(_doc(0.417, 0.9, [0.1, 0.2, 0.3, 0.4]), _doc(0.417, nan, [0.1, 0.2, 0.3, 0.4]))[0]


def _pairs_doc(pvm: list[float], teacher: list[float], photo: list[float]) -> dict:
    pairs = [asdict(PairScore(frame_id=f"p{i}", pvm_n=1, pvm_err=a, teacher_n=1, teacher_err=b, photo_sum=c,
                              photo_n=1)) for i, (a, b, c) in enumerate(zip(pvm, teacher, photo, strict=True))]
    return {"summary": {"pvm_epe": sum(pvm) / len(pvm)}, "pairs": pairs}


def test_candidate_guards_by_photometric_or_teacher() -> None:
    """G1-G3's rule guards with the photometric error, G4's amended rule (after J2) with the teacher EPE: the same
    pair of results is a candidate by one and not by the other."""
    base = _pairs_doc([0.50, 0.52, 0.54, 0.56], [0.80, 0.90, 1.00, 1.10], [0.10, 0.20, 0.30, 0.40])
    # PVM EPE per pair -0.010, -0.012, -0.010, -0.012: mean -0.011, noise 2 * 0.001155 / 2 = 0.0012 -> lower
    # photometric +0.003, +0.002, +0.003, +0.002 (worse beyond its noise); teacher EPE -0.01 on each pair
    cand = _pairs_doc([0.490, 0.508, 0.530, 0.548], [0.79, 0.89, 0.99, 1.09], [0.103, 0.202, 0.303, 0.402])
    ok, why = candidate(base, cand)
    assert not ok and "photometric +0.0025" in why
    ok, why = candidate(base, cand, guard="teacher_epe")
    assert ok and why.startswith("candidate: ") and "teacher EPE -0.010" in why
    worse_teacher = _pairs_doc([0.490, 0.508, 0.530, 0.548], [0.82, 0.91, 1.02, 1.11], [0.10, 0.20, 0.30, 0.40])
    assert candidate(base, worse_teacher)[0] and not candidate(base, worse_teacher, guard="teacher_epe")[0]
    with pytest.raises(ValueError, match="guard"):
        candidate(base, cand, guard="pvm_bad3")
