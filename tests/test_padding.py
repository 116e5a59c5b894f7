"""InputPadder: pad to a multiple of 8 and crop back (KITTI sizes)."""

from __future__ import annotations

import pytest
import torch

from optstereo.inference.padding import InputPadder


class TestInputPadder:
    @pytest.mark.parametrize(("h", "w"), [(375, 1242), (370, 1224), (376, 1241), (32, 64)])
    def test_cardinality(self, h: int, w: int) -> None:
        x = torch.rand(1, 3, h, w)
        padder = InputPadder(x.shape, divis_by=8)
        (xp,) = padder.pad(x)
        assert xp.shape[-2] % 8 == 0 and xp.shape[-1] % 8 == 0
        assert xp.shape[-2] - h < 8 and xp.shape[-1] - w < 8
        torch.testing.assert_close(padder.unpad(xp), x)

    def test_feature_kitti(self) -> None:
        left, right = torch.rand(2, 3, 375, 1242), torch.rand(2, 3, 375, 1242)
        padder = InputPadder(left.shape)
        lp, rp = padder.pad(left, right)
        assert lp.shape == rp.shape == (2, 3, 376, 1248)
        assert padder.pads == (3, 3, 0, 1)  # (left, right, top, bottom): split evenly, odd pixel bottom/right
        torch.testing.assert_close(lp[..., 0:375, :3], left[..., :, :1].expand(-1, -1, -1, 3))
        torch.testing.assert_close(lp[..., 0:375, 0], left[..., :, 0])  # replicate padding copies the edge
        torch.testing.assert_close(lp[..., 375, 3:-3], left[..., 374, :])
        disp = torch.rand(2, 1, 376, 1248)
        assert padder.unpad(disp).shape == (2, 1, 375, 1242)

    def test_feature_three_dim_and_constant(self) -> None:
        x = torch.rand(3, 10, 13)
        padder = InputPadder(x.shape)
        (xp,) = padder.pad(x)
        assert xp.shape == (3, 16, 16)
        torch.testing.assert_close(padder.unpad(xp), x)
        (zp,) = InputPadder(x.shape, mode="constant").pad(x)
        assert zp[..., 0, :].abs().sum() == 0

    def test_exception(self) -> None:
        padder = InputPadder((1, 3, 375, 1242))
        with pytest.raises(ValueError, match=r"built for \(H, W\) = \(375, 1242\), got \(1, 3, 370, 1224\)"):
            padder.pad(torch.zeros(1, 3, 370, 1224))
        with pytest.raises(ValueError, match=r"unpad expects \(\.\.\., 376, 1248\), got \(1, 1, 375, 1242\)"):
            padder.unpad(torch.zeros(1, 1, 375, 1242))
        with pytest.raises(ValueError, match="needs a shape"):
            InputPadder((5,))
        with pytest.raises(ValueError, match="divis_by must be >= 1"):
            InputPadder((4, 4), divis_by=0)
