"""A coarse-to-fine start for the GRU: D_s^0 from a pass on the pair at half size instead of zero.

The paper's update operator starts every pair from D_s^0 = 0 and walks to the disparity; on a repeating structure
(KITTI 2012's iron gate, RESULTS.md) it stops at the first period it meets. A pass at half size sees the structure
as finer than the 1/8 grid and the surroundings as larger, and a start from its answer puts the walk near the right
period. Weights trained from zero starts do not walk well from other starts (RESULTS.md: a probe), so the trainer
draws coarse starts with probability ``data.cascade_p`` and ``InferenceConfig.coarse_start`` turns them on at test
time: ``optstereo.inference.engine.run`` calls the same :func:`coarse_start` on the resized, padded pair.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from optstereo.training.losses import photometric_error, warp_right_to_left

DIVISOR = 8  # the 1/8 grid D_s lives on


def grid_start(disp: torch.Tensor) -> torch.Tensor:
    """(B, 1, H, W) disparity in pixels of an (H, W) pair, H and W multiples of 8 -> (B, 1, H/8, W/8) in 1/8-grid
    pixels: the mean of each 8x8 cell, divided by 8 (the units of the network's D_s)."""
    if disp.shape[-2] % DIVISOR or disp.shape[-1] % DIVISOR:
        raise ValueError(f"grid_start needs H and W divisible by {DIVISOR}, got {tuple(disp.shape[-2:])}")
    return F.avg_pool2d(disp.float(), DIVISOR) / DIVISOR


def half_size(height: int, width: int, min_width: int = DIVISOR) -> tuple[int, int]:
    """(h, w) of the coarse pass of an (H, W) batch: half, rounded down to multiples of 8 (at least 8), and never
    narrower than ``min_width`` (the network's narrowest input) unless the batch itself is."""
    w = max(DIVISOR, width // 2 // DIVISOR * DIVISOR, min(min_width, width))
    return max(DIVISOR, height // 2 // DIVISOR * DIVISOR), w


@torch.no_grad()
def coarse_start(model: nn.Module, left: torch.Tensor, right: torch.Tensor, iters: int | None) -> torch.Tensor:
    """D_s^0 for a (B, 3, H, W) batch (H, W multiples of 8) from ``model`` on the batch at :func:`half_size`.

    The half-size pair is area-averaged, its full-resolution disparity brought back to (H, W) bilinearly and times
    W / w, then averaged onto the 1/8 grid (:func:`grid_start`). No gradient flows into it (the GRU is trained to
    refine a start, not to make one).
    """
    h, w = half_size(left.shape[-2], left.shape[-1], getattr(model, "min_width", DIVISOR))  # HITNet: any width
    small_l = F.interpolate(left, size=(h, w), mode="area")
    small_r = F.interpolate(right, size=(h, w), mode="area")
    _, full = model(small_l, small_r, iters=iters, test_mode=True)
    up = F.interpolate(full.float(), size=left.shape[-2:], mode="bilinear", align_corners=False)
    return grid_start(up * (left.shape[-1] / w))


#: Side of the box window :func:`photometric_select` averages each candidate's per-pixel photometric error over (on
#: top of SSIM's own 3x3): 9x9 pixels of support in all, the size of a census window, fixed before any scoring.
SELECT_WINDOW = 7


def photometric_select(left: np.ndarray, right: np.ndarray, candidates: Sequence[np.ndarray],
                       window: int = SELECT_WINDOW, max_jump: float = 0.0) -> np.ndarray:
    """Per pixel, the candidate disparity whose right-to-left warp matches the left view best; no ground truth.

    ``left``, ``right``: (H, W, 3) uint8; ``candidates``: (H, W) float32 disparities of that pair (an exact tie goes
    to the first). The error is :func:`photometric_costs`. ``max_jump`` > 0: another candidate is only chosen where
    it lies within that many pixels of the first (a repeating structure matches as well one period away, and there
    the first candidate, the coarse start, is the one to trust: :func:`jump_limit`). Returns (H, W) float32.
    """
    costs = photometric_costs(left, right, candidates, window)  # checks the shapes first
    return choose(np.stack(candidates).astype(np.float32), costs, max_jump)


@torch.no_grad()
def photometric_costs(left: np.ndarray, right: np.ndarray, candidates: Sequence[np.ndarray],
                      window: int = SELECT_WINDOW) -> np.ndarray:
    """(K, H, W) float32: per candidate disparity, how badly the right view warped by it matches the left.

    ``left``, ``right``: (H, W, 3) uint8; ``candidates``: K (H, W) float32 disparities. The error is the
    reconstruction loss's own per-pixel form (``optstereo.training.losses.photometric_error``: 0.85 (1 - SSIM 3x3) / 2
    + 0.15
    L1), 1 where the warp leaves the image, then averaged over a ``window`` x ``window`` box so that one pixel's
    noise does not decide.
    """
    if not len(candidates):
        raise ValueError("photometric_select needs at least one candidate")
    shape = left.shape[:2]
    if right.shape[:2] != shape or any(c.shape != shape for c in candidates):
        raise ValueError(f"photometric_select: the pair and every candidate must be {shape}, got right "
                         f"{right.shape[:2]} and candidates {[c.shape for c in candidates]}")
    left_t = torch.from_numpy(np.ascontiguousarray(left)).permute(2, 0, 1)[None].float() / 255.0
    right_t = torch.from_numpy(np.ascontiguousarray(right)).permute(2, 0, 1)[None].float() / 255.0
    costs = []
    for disp in candidates:
        warped, valid = warp_right_to_left(right_t, torch.from_numpy(np.asarray(disp, np.float32))[None, None])
        cost = torch.where(valid, photometric_error(left_t, warped), torch.ones(()))
        costs.append(F.avg_pool2d(cost, window, 1, window // 2, count_include_pad=False)[0, 0])
    return torch.stack(costs).numpy()


def choose(disps: np.ndarray, costs: np.ndarray, max_jump: float = 0.0) -> np.ndarray:
    """(K, H, W) candidate disparities and their (K, H, W) costs -> (H, W) float32: per pixel the lowest-cost
    candidate (the first of equal ones), a candidate other than the first only within ``max_jump`` pixels of it
    when ``max_jump`` > 0."""
    if max_jump > 0:
        costs = costs.copy()  # the caller's costs serve other limits (pipelines.cascade_select calibrate)
        costs[1:][np.abs(disps[1:] - disps[:1]) > max_jump] = np.inf
    best = costs.argmin(axis=0)  # argmin takes the first of equal minima: the preferred candidate
    return np.take_along_axis(disps, best[None], axis=0)[0].astype(np.float32)


def jump_limit(width: int, jump: float) -> float:
    """The ``max_jump`` of :func:`photometric_select` in pixels for a pair ``width`` pixels wide and
    ``InferenceConfig.select_jump`` = ``jump`` (a fraction of the width, so that the choice does not change when
    the pair is resized; 0 = no limit)."""
    if not 0 <= jump < float("inf"):
        raise ValueError(f"select_jump must be >= 0 and finite, got {jump}")
    return jump * width
