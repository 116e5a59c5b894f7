"""LR-check kernel vs the NumPy reference, and hand-computed cases (edge columns, rounding, NaNs)."""

from __future__ import annotations

import numpy as np
import pytest
from naive_pvm import naive_lr_check

from pvm_labeler.common.errors import InputError
from pvm_labeler.multiscale import lr_check


class TestLRCheck:
    @pytest.mark.parametrize("threshold", [0.0, 0.5, 1.0, 3.0])
    def test_feature_matches_naive(self, rng, threshold):
        h, w = 11, 23
        disp_l = rng.uniform(0, 8, size=(h, w)).astype(np.float32)
        disp_r = disp_l.copy()
        disp_r += rng.normal(0, 1.0, size=(h, w)).astype(np.float32)
        disp_r = np.abs(disp_r)
        disp_l[rng.random((h, w)) < 0.15] = np.nan
        disp_r[rng.random((h, w)) < 0.15] = np.nan
        disp_l[:, :3] = rng.uniform(0, 8, size=(h, 3)).astype(np.float32)  # x - d < 0 at the left edge
        disp_r[:, -3:] = rng.uniform(0, 8, size=(h, 3)).astype(np.float32)  # x + d >= W at the right edge
        got_l, got_r = lr_check(disp_l, disp_r, threshold)
        ref_l, ref_r = naive_lr_check(disp_l, disp_r, threshold)
        np.testing.assert_array_equal(got_l, ref_l)
        np.testing.assert_array_equal(got_r, ref_r)
        if threshold >= 1.0:
            assert 0 < np.isfinite(got_l).sum() < np.isfinite(disp_l).sum()

    def test_feature_hand_computed(self):
        nan = np.nan
        #                  x: 0    1    2    3    4    5
        disp_l = np.array([[2.0, 2.0, 2.0, 2.4, 2.6, 1.0]], np.float32)
        disp_r = np.array([[2.0, 2.0, 5.0, 2.0, nan, 2.0]], np.float32)
        out_l, out_r = lr_check(disp_l, disp_r, 1.0)
        # x=0,1: x - d < 0 (outside the right image). x=2 -> xr=0 (2.0 ok). x=3: 3-2.4=0.6 -> rounds to 1 (2.0, ok).
        # x=4: 4-2.6=1.4 -> 1 (2.0, |0.6| ok). x=5: 5-1=4 -> NaN in the right view -> rejected.
        np.testing.assert_array_equal(out_l, np.array([[nan, nan, 2.0, 2.4, 2.6, nan]], np.float32))
        # Right: x=0 -> xl=2 (2.0 ok); x=1 -> 3 (2.4 ok); x=2 -> 7 outside; x=3 -> 5 (1.0, |1.0| <= 1 ok);
        # x=4 NaN; x=5 -> 7 outside.
        np.testing.assert_array_equal(out_r, np.array([[2.0, 2.0, nan, 2.0, nan, nan]], np.float32))
        out_l, out_r = lr_check(disp_l, disp_r, 0.5)
        assert np.isnan(out_l[0, 4]) and np.isnan(out_r[0, 3])  # |2.6 - 2.0| = 0.6 and |2.0 - 1.0| = 1.0 > 0.5

    def test_exception(self):
        with pytest.raises(InputError, match="must be \\(H, W\\) of equal shape"):
            lr_check(np.zeros((3, 4), np.float32), np.zeros((3, 5), np.float32), 1.0)
        with pytest.raises(InputError, match="LR threshold must be >= 0 px, got -1"):
            lr_check(np.zeros((3, 4), np.float32), np.zeros((3, 4), np.float32), -1.0)
