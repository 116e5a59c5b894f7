"""HITNet tile hypotheses: slanted-plane evaluation, coarse-to-fine upsampling, initial and warped matching costs.

A hypothesis map is (B, HYP_DIM, h, w) float32, one hypothesis per tile of TILE x TILE feature pixels:
    channel 0      d: the disparity at the tile centre, in full-resolution pixels (positive, left(x) matches
                   right(x - d)), whatever the level;
    channels 1, 2  dx, dy: the plane's slants, disparity pixels per full-resolution pixel;
    channels 3..   p: the learned descriptor (DESC_DIM channels).

Tile centre convention: pixel centres sit at integer coordinates; a tile (i, j) that covers ``size`` full-resolution
pixels per side spans columns j * size .. j * size + size - 1, so its centre is x_c = j * size + (size - 1) / 2 (the
mean of its pixel coordinates; y_c likewise). The plane at a pixel (x, y) is d(x, y) = d + dx (x - x_c) + dy (y - y_c);
with an even size the centre falls between pixels and the plane is evaluated at the offsets +-0.5, +-1.5, ....
The same rule gives the children of a coarse tile: their centres lie at +-size / 4 from the parent's centre.

Reference: Tankovich et al., "HITNet: Hierarchical Iterative Tile Refinement Network for Real-time Stereo
Matching", CVPR 2021 (Sections 3.2-3.4).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

TILE = 4  # tile side in feature pixels of its level (the paper's 4x4 tiles)
DESC_DIM = 13  # the paper's descriptor p: with d, dx, dy a hypothesis has 16 channels
HYP_DIM = 3 + DESC_DIM


def _repeat(t: torch.Tensor, factor: int) -> torch.Tensor:
    """Nearest-neighbour upsampling by an integer factor: (B, C, h, w) -> (B, C, h * factor, w * factor)."""
    return t.repeat_interleave(factor, dim=-2).repeat_interleave(factor, dim=-1)


def eval_planes(hyp: torch.Tensor, factor: int, spacing: float) -> torch.Tensor:
    """Each tile's plane at a factor x factor grid of points ``spacing`` full-resolution pixels apart.

    The grid is centred on the tile centre: offsets (k - (factor - 1) / 2) * spacing, k = 0..factor - 1.

    Args:
        hyp: (B, >= 3, h, w) float hypotheses (d, dx, dy, ...).
        factor: points per tile side.
        spacing: distance between neighbouring points, full-resolution pixels.

    Returns:
        (B, 1, h * factor, w * factor) float disparity in full-resolution pixels.
    """
    h, w = hyp.shape[-2:]
    offsets = (torch.arange(factor, device=hyp.device, dtype=hyp.dtype) - (factor - 1) / 2) * spacing
    off_x = offsets.repeat(w).view(1, 1, 1, w * factor)
    off_y = offsets.repeat(h).view(1, 1, h * factor, 1)
    return _repeat(hyp[:, 0:1], factor) + _repeat(hyp[:, 1:2], factor) * off_x + _repeat(hyp[:, 2:3], factor) * off_y


def planes_to_pixels(hyp: torch.Tensor, tile_px: int, size: tuple[int, int]) -> torch.Tensor:
    """Slanted-plane upsampling to full resolution: (B, HYP_DIM, h, w) -> (B, 1, H, W), H, W = ``size``.

    ``tile_px`` is the tile side in full-resolution pixels; tiles that stick out past ``size`` (the coarse levels
    round their sizes up) are cropped.
    """
    return eval_planes(hyp, tile_px, 1.0)[..., : size[0], : size[1]]


def upsample_hypotheses(hyp: torch.Tensor, fine_tile_px: int, size: tuple[int, int]) -> torch.Tensor:
    """Coarse tiles -> the 2 x 2 child tiles of each: d from the parent's plane at the child centres, dx, dy, p copied.

    Args:
        hyp: (B, HYP_DIM, h, w) hypotheses of the coarse level.
        fine_tile_px: side of a child tile in full-resolution pixels (half the parent's).
        size: (h', w') tile grid of the fine level (<= (2h, 2w)); the excess is cropped.

    Returns:
        (B, HYP_DIM, h', w').
    """
    disp = eval_planes(hyp, 2, float(fine_tile_px))
    return torch.cat([disp, _repeat(hyp[:, 1:], 2)], dim=1)[..., : size[0], : size[1]]


def pad_to_tiles(feat: torch.Tensor) -> torch.Tensor:
    """Replicate-pad (B, C, H, W) at the bottom/right to multiples of TILE (coarse levels round up)."""
    pad_h, pad_w = (-feat.shape[-2]) % TILE, (-feat.shape[-1]) % TILE
    if pad_h == 0 and pad_w == 0:
        return feat
    return F.pad(feat, (0, pad_w, 0, pad_h), mode="replicate")


def shift_rows(feat: torch.Tensor, disp: torch.Tensor) -> torch.Tensor:
    """feat sampled at (x - disp(x, y), y), linear along x, zeros outside: (B, C, H, W), disp (B, 1, H, W)."""
    _, _, h, w = feat.shape
    src_x = torch.arange(w, device=feat.device, dtype=feat.dtype).view(1, 1, w) - disp[:, 0]
    # align_corners=True maps -1 / +1 to the first / last pixel centre, so rows land exactly on rows.
    grid_x = src_x * (2.0 / max(w - 1, 1)) - 1.0
    grid_y = torch.linspace(-1.0, 1.0, h, device=feat.device, dtype=feat.dtype).view(1, h, 1).expand_as(grid_x)
    grid = torch.stack([grid_x, grid_y], dim=-1)
    return F.grid_sample(feat, grid, mode="bilinear", padding_mode="zeros", align_corners=True)


def tile_costs(feat_left: torch.Tensor, feat_right: torch.Tensor, hyp: torch.Tensor, stride: int,
               radius: int) -> torch.Tensor:
    """Matching costs of each tile's slanted plane at its TILE x TILE feature pixels (HITNet's warping).

    Every feature pixel takes the plane's disparity at its centre, shifted by k = -radius..radius feature pixels
    (the paper's d - 1, d, d + 1), and compares its feature with the right feature warped by it (mean L1 over
    channels). The plane is detached first, as RAFT detaches its lookup: the loss reaches d through the updates.

    Args:
        feat_left, feat_right: (B, C, TILE * h, TILE * w) features of the level (padded with ``pad_to_tiles``).
        hyp: (B, HYP_DIM, h, w) hypotheses.
        stride: full-resolution pixels per feature pixel of the level.
        radius: disparity offsets either side, in feature pixels.

    Returns:
        (B, TILE * TILE * (2 radius + 1), h, w) float costs (offset-major, then the tile's pixels row by row).
    """
    disp = eval_planes(hyp.detach(), TILE, float(stride)) / stride
    costs = []
    for offset in range(-radius, radius + 1):
        warped = shift_rows(feat_right, disp + offset)
        cost = (feat_left - warped).abs().mean(dim=1, keepdim=True)
        costs.append(F.pixel_unshuffle(cost, TILE))
    return torch.cat(costs, dim=1)


def cost_volume(tile_left: torch.Tensor, tile_right: torch.Tensor, num_disp: int) -> torch.Tensor:
    """The local cost volume of a level's initialisation: mean L1 distance of tile features per integer disparity.

    Tile j of the left matches column TILE * j - d of the right tile features, which keep every column (they come
    from the same 4x4 convolution applied with stride (TILE, 1)).

    Args:
        tile_left: (B, C, h, w) left tile features.
        tile_right: (B, C, h, TILE * w) right tile features at every column.
        num_disp: disparities 0..num_disp - 1, in feature pixels of the level.

    Returns:
        (B, num_disp, h, w) float cost, +inf where TILE * j - d < 0 (no match; d = 0 always has one).
    """
    w = tile_left.shape[-1]
    planes = []
    for d in range(num_disp):
        first = min(-(-d // TILE), w)  # the first tile whose match column TILE * j - d is >= 0
        cols = tile_right[..., TILE * first - d :: TILE][..., : w - first]
        cost = (tile_left[..., first:] - cols).abs().mean(dim=1)
        planes.append(F.pad(cost, (first, 0), value=float("inf")))  # constant fill: no gradient reaches it
    return torch.stack(planes, dim=1)


def soft_argmin(volume: torch.Tensor) -> torch.Tensor:
    """Differentiable disparity of a cost volume, sum_d d softmax(-cost)_d: (B, D, h, w) -> (B, 1, h, w) float.

    Supervising it with the labels makes the lowest cost fall on the labelled disparity, the job of HITNet's
    initialisation loss (docs/optstereo.md, "PVM-HITNet").
    """
    disps = torch.arange(volume.shape[1], device=volume.device, dtype=volume.dtype).view(1, -1, 1, 1)
    return (torch.softmax(-volume, dim=1) * disps).sum(dim=1, keepdim=True)


def tiles_to_pixels(disp: torch.Tensor, tile_px: int, size: tuple[int, int]) -> torch.Tensor:
    """Fronto-parallel tiles to full resolution: (B, 1, h, w) -> (B, 1, H, W), each tile's value repeated."""
    return _repeat(disp, tile_px)[..., : size[0], : size[1]]
