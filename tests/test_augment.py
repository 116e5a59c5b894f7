"""Flip-swap (paper Section III-C) on NumPy and torch, checked on a scene with distinct left/right labels."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from optstereo.training.augment import flip_swap
from optstereo.training.losses import warp_right_to_left

NAN = np.float32(np.nan)


def occlusion_scene(rng: np.random.Generator, height: int = 8, width: int = 64) -> tuple[np.ndarray, ...]:
    """Background (d = 3) on the left half, a nearer foreground (d = 9) on the right half, with occlusion.

    Right pixel u sees the left pixels x with x - d(x) = u; the largest disparity (nearest) wins; u with no
    candidate is disoccluded (random texture, NaN label). Left pixels hidden in the right view get NaN. So the
    left and right labels differ near the depth edge, which is what catches RAFT-Stereo's flip bug.

    Returns:
        left, right (H, W, 3) uint8; label_left, label_right (H, W) float32, NaN = no match.
    """
    d_left = np.where(np.arange(width) < width // 2, 3, 9)
    left = rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8)
    right = rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8)
    label_left = np.full((height, width), NAN, dtype=np.float32)
    label_right = np.full((height, width), NAN, dtype=np.float32)
    winner = np.full(width, -1)
    for x in range(width):
        u = x - d_left[x]
        if u >= 0 and (winner[u] < 0 or d_left[x] > d_left[winner[u]]):
            winner[u] = x
    for u, x in enumerate(winner):
        if x >= 0:
            right[:, u] = left[:, x]
            label_right[:, u] = d_left[x]
            label_left[:, x] = d_left[x]
    return left, right, label_left, label_right


def _warp_error(left: np.ndarray, right: np.ndarray, label: np.ndarray) -> np.ndarray:
    """|left - right warped by label| per pixel (max over channels); NaN where the label is NaN."""
    lt = torch.from_numpy(left).permute(2, 0, 1)[None].float()
    rt = torch.from_numpy(right).permute(2, 0, 1)[None].float()
    disp = torch.from_numpy(np.nan_to_num(label, nan=0.0))[None, None]
    warped, _ = warp_right_to_left(rt, disp)
    err = (lt - warped).abs().amax(dim=1)[0].numpy()
    return np.where(np.isfinite(label), err, np.nan)


class TestFlipSwap:
    def test_feature_numpy_twice_is_identity(self, rng: np.random.Generator) -> None:
        sample = occlusion_scene(rng)
        once = flip_swap(*sample)
        twice = flip_swap(*once)
        for a, b in zip(sample, twice, strict=True):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(once[0], sample[1][:, ::-1])  # new left = flipped right
        np.testing.assert_array_equal(once[2], sample[3][:, ::-1])  # new left label = flipped RIGHT label
        assert all(a.flags.c_contiguous for a in once)

    def test_feature_torch_twice_is_identity(self) -> None:
        left, right = torch.rand(2, 3, 4, 6), torch.rand(2, 3, 4, 6)
        label_l, label_r = torch.rand(2, 1, 4, 6), torch.rand(2, 1, 4, 6)
        once = flip_swap(left, right, label_l, label_r)
        torch.testing.assert_close(once[0], right.flip(-1))
        torch.testing.assert_close(once[2], label_r.flip(-1))
        for a, b in zip((left, right, label_l, label_r), flip_swap(*once), strict=True):
            torch.testing.assert_close(a, b)

    def test_feature_labels_consistent_after_flip(self, rng: np.random.Generator) -> None:
        left, right, label_l, label_r = occlusion_scene(rng)
        assert np.nanmax(_warp_error(left, right, label_l)) < 1e-3  # the scene itself is consistent
        new_left, new_right, new_label_l, _ = flip_swap(left, right, label_l, label_r)
        err = _warp_error(new_left, new_right, new_label_l)
        assert np.isfinite(err).sum() > 0.7 * err.size and np.nanmax(err) < 1e-3
        # RAFT-Stereo's flip keeps the left label: inconsistent near the depth edge.
        wrong = _warp_error(new_left, new_right, label_l[:, ::-1].copy())
        assert np.nanmax(wrong) > 10

    def test_smoke_none_labels(self) -> None:
        left, right = np.zeros((4, 5, 3), np.uint8), np.ones((4, 5, 3), np.uint8)
        out = flip_swap(left, right, np.zeros((4, 5), np.float32), None)
        assert out[2] is None and out[3].shape == (4, 5)

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match=r"left/right shapes differ: \(4, 5, 3\) vs \(4, 6, 3\)"):
            flip_swap(np.zeros((4, 5, 3)), np.zeros((4, 6, 3)), None, None)
        with pytest.raises(ValueError, match=r"must be \(H, W\) or \(H, W, C\), got shape \(1, 4, 5, 3\)"):
            flip_swap(np.zeros((1, 4, 5, 3)), np.zeros((1, 4, 5, 3)), None, None)
        with pytest.raises(TypeError, match="got list"):
            flip_swap([[1]], [[1]], None, None)


def test_flip_swap_refuses_the_other_layout_of_each_kind() -> None:
    """A torch (H, W, 3) image had its colours mirrored (RGB -> BGR) and a NumPy (3, H, W) one its rows, silently."""
    hwc = np.random.default_rng(0).integers(0, 255, (16, 24, 3), dtype=np.uint8)
    with pytest.raises(ValueError, match=r"torch inputs must be \(\.\.\., H, W\).*x.permute\(2, 0, 1\)"):
        flip_swap(torch.from_numpy(hwc), torch.from_numpy(hwc), None, None)
    chw = np.ascontiguousarray(hwc.transpose(2, 0, 1))
    with pytest.raises(ValueError, match=r"numpy inputs must be \(H, W\) or \(H, W, C\)"):
        flip_swap(chw, chw, None, None)
    new_left, _, _, _ = flip_swap(torch.from_numpy(chw), torch.from_numpy(chw), None, None)  # (3, H, W): columns
    assert torch.equal(new_left, torch.from_numpy(chw).flip(-1))
    assert np.array_equal(flip_swap(hwc, hwc, None, None)[0], hwc[:, ::-1])


def test_a_flip_swap_probability_above_1_is_refused() -> None:
    from optstereo.data.transforms import TrainTransform  # lazy: one test's

    with pytest.raises(ValueError, match=r"flip_swap_p is a probability in \[0, 1\], got 2.0"):
        TrainTransform(flip_swap_p=2.0)
