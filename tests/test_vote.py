"""Voting kernel vs the NumPy reference, and the vote's semantics on hand-built stacks."""

from __future__ import annotations

import numpy as np
import pytest
from naive_pvm import naive_vote

from pvm_labeler.common.errors import InputError
from pvm_labeler.config import LabelerConfig
from pvm_labeler.multiscale import vote

# float32 outputs of a float64 computation: the kernel and np.std/np.median may differ in the last float32 ulp.
RTOL, ATOL = 1e-6, 1e-6


def _random_stack(rng: np.random.Generator, k: int = 5, h: int = 9, w: int = 13, nan_frac: float = 0.1):
    base = rng.uniform(0, 40, size=(1, h, w))
    disp = (base + rng.normal(0, 0.8, size=(k, h, w))).astype(np.float32)
    conf = rng.uniform(0.5, 1.0, size=(1, h, w)) + rng.normal(0, 0.06, size=(k, h, w))
    conf = conf.astype(np.float32)
    disp[rng.random(disp.shape) < nan_frac] = np.nan
    conf[rng.random(conf.shape) < nan_frac / 2] = np.nan
    disp[:, :, 0] = np.nan  # an invalid edge column, as SGM produces at x < d
    return disp, conf


class TestVote:
    @pytest.mark.parametrize("mode", ["finest", "median", "mean", "weighted"])
    @pytest.mark.parametrize("k", [1, 4, 6])
    def test_feature_matches_naive(self, rng, mode, k):
        disp, conf = _random_stack(rng, k=k)
        factors = np.arange(1, k + 1) + np.r_[0.0, rng.uniform(-1, 1, k - 1)]
        cfg = LabelerConfig(k=k, kappa1=1.0, kappa2=0.06, label_mode=mode)
        got = vote(disp, conf, cfg, factors)
        ref = naive_vote(disp, conf, 1.0, 0.06, mode, 1.0 / factors**2, c2_scale=cfg.c2_scale)
        for g, r in zip(got, ref, strict=True):
            np.testing.assert_allclose(g, r, rtol=RTOL, atol=ATOL, equal_nan=True)
        # The random stack must exercise both outcomes, or the comparison proves little.
        assert 0 < np.isfinite(got[0]).sum() < np.isfinite(got[2]).sum() or k == 1

    def test_feature_hand_computed(self):
        # One pixel, K = 4 (binary-exact values): disparities 10, 11, 10, 11 -> std 0.5;
        # c = 0.75, 0.75, 0.5, 0.5 -> mean 0.625, std 0.125.
        disp = np.array([10, 11, 10, 11], np.float32).reshape(4, 1, 1)
        conf = np.array([0.75, 0.75, 0.5, 0.5], np.float32).reshape(4, 1, 1)
        cfg = LabelerConfig(k=4, kappa1=1.0, kappa2=0.25, c2_scale=0.25, label_mode="finest")
        label, confidence, c1, c2 = vote(disp, conf, cfg)
        assert c1[0, 0] == 0.5 and c2[0, 0] == 0.125
        assert label[0, 0] == 10.0
        assert confidence[0, 0] == 0.625 * 0.5 * 0.5
        # The soft confidence divides C2 by c2_scale, the hard vote compares it with kappa2: two settings.
        _, confidence, _, _ = vote(disp, conf, LabelerConfig(k=4, kappa1=1.0, kappa2=0.25, c2_scale=0.5,
                                                             label_mode="finest"))
        assert confidence[0, 0] == 0.625 * 0.5 * 0.75
        # C1 exactly at kappa1 votes against (V counts C1 >= kappa1).
        label, confidence, _, _ = vote(disp, conf, LabelerConfig(k=4, kappa1=0.5, kappa2=0.25, label_mode="finest"))
        assert np.isnan(label[0, 0]) and confidence[0, 0] == 0.0
        label, _, _, _ = vote(disp, conf, LabelerConfig(k=4, kappa1=1.0, kappa2=0.125, label_mode="finest"))
        assert np.isnan(label[0, 0])
        label, _, _, _ = vote(disp, conf, LabelerConfig(k=4, kappa1=1.0, kappa2=0.25, label_mode="median"))
        assert label[0, 0] == 10.5

    def test_feature_one_invalid_scale_rejects(self):
        disp = np.full((3, 2, 2), 7.0, np.float32)
        conf = np.full((3, 2, 2), 0.9, np.float32)
        disp[2, 0, 0] = np.nan
        conf[1, 1, 1] = np.nan
        label, confidence, c1, _ = vote(disp, conf, LabelerConfig(k=3, label_mode="finest"))
        assert np.isnan(label[0, 0]) and np.isnan(label[1, 1]) and np.isnan(c1[0, 0])
        assert label[0, 1] == 7.0 and confidence[0, 1] == pytest.approx(0.9, abs=1e-6)

    def test_exception(self):
        with pytest.raises(InputError, match=r"disp/conf must be \(K, H, W\) of equal shape"):
            vote(np.zeros((2, 3, 3), np.float32), np.zeros((2, 3, 4), np.float32), LabelerConfig(k=2))
        with pytest.raises(InputError, match="label_mode 'weighted' needs 2 scale factors"):
            vote(np.zeros((2, 3, 3), np.float32), np.zeros((2, 3, 3), np.float32),
                 LabelerConfig(k=2, label_mode="weighted"))
