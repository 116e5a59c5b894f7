"""pipelines/studies/adapt_teacher_check.py: one frame's scores against its PVM labels and the teacher's consistent
pixels in PVM's holes, and the photometric error split at the band whose match may leave the right image."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import make_synthetic_pair

from pipelines.studies import adapt_teacher_check as study


def test_frame_scores_by_hand(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    left, right = make_synthetic_pair(np.random.default_rng(0), 24, 48, disp=4)  # left(x) == right(x - 4)
    label = np.full((24, 48), np.nan, np.float32)
    label[:, 20:30] = 4.0  # PVM labels a band, max 4: columns x < 4 are the band
    np.savez(tmp_path / "f.npz", left=np.full((24, 48), 5.0, np.float32), right=np.full((24, 48), 5.0, np.float32))
    prediction = np.full((24, 48), 4.0, np.float32)
    prediction[:, 20:30] = 4.5  # 0.5 px off on PVM's pixels
    monkeypatch.setattr(study, "infer", lambda model, a, b: prediction)
    score, photo = study.frame_scores(None, SimpleNamespace(frame_id="f", left=left, right=right, label=label),
                                      tmp_path)
    assert score.pvm_n == 240 and score.pvm_err == pytest.approx(120.0)
    # the teacher says 5 in both views: consistent where x - 5 >= 0; scored in PVM's holes only, 1 px off each
    assert score.teacher_n == 24 * (48 - 10 - 5) and score.teacher_err == pytest.approx(score.teacher_n)
    assert photo["photometric_band"] == pytest.approx(1.0)  # x < 4: the warp leaves the image, charged 1
    assert photo["photometric_beyond_band"] < 0.05  # the true shift elsewhere
