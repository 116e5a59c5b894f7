"""pvm_labeler/dense.py: the row fill by hand, and which search range the evaluation's dense-SGM baseline uses."""

from __future__ import annotations

import numpy as np
import pytest

import pvm_labeler.dense as ds
from pvm_labeler.config import LabelerConfig

N = np.nan


def test_fill_rows_nearest_by_hand() -> None:
    disp = np.array([[N, 2, N, N, 5, N], [N, N, N, N, N, N], [7, N, N, N, N, N]], np.float32)
    want = np.array([[2, 2, 2, 5, 5, 5], [N, N, N, N, N, N], [7, 7, 7, 7, 7, 7]], np.float32)
    np.testing.assert_array_equal(ds.fill_rows_nearest(disp), want)
    tie = np.array([[1, N, 3]], np.float32)
    assert ds.fill_rows_nearest(tie)[0, 1] == 1  # a tie takes the left value


@pytest.mark.parametrize(("set_max", "pair_max", "used"), [(192, 60, 192), (None, 60, 60), (None, None, 64)])
def test_dense_sgm_search_range_and_fill(monkeypatch: pytest.MonkeyPatch, set_max, pair_max, used) -> None:
    seen = []

    def fake_sgm_left(left, right, cfg, max_disp):
        seen.append(max_disp)
        return np.array([[N, 4, N]], np.float32), 0.5

    monkeypatch.setattr(ds, "sgm_left", fake_sgm_left)
    disp, seconds = ds.dense_sgm(np.zeros((1, 3, 3), np.uint8), np.zeros((1, 3, 3), np.uint8), LabelerConfig(),
                                 set_max, pair_max)
    assert seen == [used] and seconds == 0.5
    np.testing.assert_array_equal(disp, [[4, 4, 4]])
