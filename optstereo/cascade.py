"""A coarse-to-fine start for the GRU: D_s^0 from a pass on the pair at half size instead of zero.

The paper's update operator starts every pair from D_s^0 = 0 and walks to the disparity; on a repeating structure
(KITTI 2012's iron gate, RESULTS.md) it stops at the first period it meets. A pass at half size sees the structure
as finer than the 1/8 grid and the surroundings as larger, and a start from its answer puts the walk near the right
period. Weights trained from zero starts do not walk well from other starts (RESULTS.md: a probe), so the trainer
draws coarse starts with probability ``data.cascade_p`` and ``ModelConfig.cascade`` turns them on at test time.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

DIVISOR = 8  # the 1/8 grid D_s lives on


def grid_start(disp: torch.Tensor) -> torch.Tensor:
    """(B, 1, H, W) disparity in pixels of an (H, W) pair, H and W multiples of 8 -> (B, 1, H/8, W/8) in 1/8-grid
    pixels: the mean of each 8x8 cell, divided by 8 (the units of the network's D_s)."""
    if disp.shape[-2] % DIVISOR or disp.shape[-1] % DIVISOR:
        raise ValueError(f"grid_start needs H and W divisible by {DIVISOR}, got {tuple(disp.shape[-2:])}")
    return F.avg_pool2d(disp.float(), DIVISOR) / DIVISOR


def half_size(height: int, width: int) -> tuple[int, int]:
    """(h, w) of the coarse pass of an (H, W) batch: half, rounded down to multiples of 8 (at least 8)."""
    return max(DIVISOR, height // 2 // DIVISOR * DIVISOR), max(DIVISOR, width // 2 // DIVISOR * DIVISOR)


@torch.no_grad()
def coarse_start(model: nn.Module, left: torch.Tensor, right: torch.Tensor, iters: int | None) -> torch.Tensor:
    """D_s^0 for a (B, 3, H, W) batch (H, W multiples of 8) from ``model`` on the batch at :func:`half_size`.

    The half-size pair is area-averaged, its full-resolution disparity brought back to (H, W) bilinearly and times
    W / w, then averaged onto the 1/8 grid (:func:`grid_start`). No gradient flows into it (the GRU is trained to
    refine a start, not to make one).
    """
    h, w = half_size(left.shape[-2], left.shape[-1])
    small_l = F.interpolate(left, size=(h, w), mode="area")
    small_r = F.interpolate(right, size=(h, w), mode="area")
    _, full = model(small_l, small_r, iters=iters, test_mode=True)
    up = F.interpolate(full.float(), size=left.shape[-2:], mode="bilinear", align_corners=False)
    return grid_start(up * (left.shape[-1] / w))
