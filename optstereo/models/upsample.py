"""Upsampling modules: 1/8 disparity D_s^k -> full-resolution D^k (values scale x8 with resolution)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from optstereo.models.layers import conv3x3, use_channels_last


def upsample_disp(disp: torch.Tensor, factor: int = 8) -> torch.Tensor:
    """Bilinear upsampling of a disparity map, values multiplied by the factor.

    align_corners=False: low-res pixel i covers full-res pixels [f i, f i + f - 1], which is how the
    stride-8 encoder places its outputs. Shapes: (B, 1, h, w) -> (B, 1, f h, f w).
    """
    return factor * F.interpolate(disp, scale_factor=factor, mode="bilinear", align_corners=False)


class ConvUpsampler(nn.Module):
    """The paper's upsampling module: an upsampling layer followed by two conv layers.

    D^k = U + Conv3x3(ReLU(Conv3x3([U / f, I_l]))), U = f * bilinear_up(D_s^k), f = 8.
    Design choices (the paper is silent): the two convs predict a residual on top of the bilinear
    upsampling, so an untrained module already outputs a sensible full-resolution disparity; the
    normalised left image I_l is concatenated as guidance so the convs can sharpen edges where the
    image has them; U is divided by f so the conv input stays O(1..30) like the 1/8 disparity.

    Shapes: disp_low (B, 1, H/8, W/8), image (B, 3, H, W) in [-1, 1] -> (B, 1, H, W).
    """

    def __init__(self, factor: int = 8, width: int = 32, guide_channels: int = 3) -> None:
        super().__init__()
        self.factor = factor
        self.conv1 = conv3x3(1 + guide_channels, width)
        self.conv2 = conv3x3(width, 1)
        self.relu = nn.ReLU(inplace=True)

    def forward(self, disp_low: torch.Tensor, hidden: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        up = upsample_disp(disp_low, self.factor)
        x = torch.cat([up / self.factor, image.to(up.dtype)], dim=1).to(self.conv1.weight.dtype)
        if use_channels_last(x):  # oneDNN convolves NHWC on CPU: no layout copy of the wide full-resolution layer
            x = x.contiguous(memory_format=torch.channels_last)
        return up + self.conv2(self.relu(self.conv1(x))).float()  # one channel: channels-last is contiguous


class ConvexUpsampler(nn.Module):
    """RAFT's convex upsampling (beyond the paper; ``upsampler="convex"``).

    A mask head on h predicts, for each of the f x f sub-pixels of a 1/8 pixel, softmax weights over
    the 3x3 neighbourhood of f * D_s; the full-resolution disparity is that convex combination.

    Shapes: disp_low (B, 1, h, w), hidden (B, hidden_dim, h, w) -> (B, 1, f h, f w).
    """

    def __init__(self, hidden_dim: int, factor: int = 8, width: int = 256) -> None:
        super().__init__()
        self.factor = factor
        self.mask = nn.Sequential(
            conv3x3(hidden_dim, width), nn.ReLU(inplace=True), nn.Conv2d(width, factor * factor * 9, kernel_size=1)
        )

    def forward(self, disp_low: torch.Tensor, hidden: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        b, _, h, w = disp_low.shape
        f = self.factor
        # 0.25 scaling of the mask logits as in RAFT (balances the gradients of the mask head).
        mask = (0.25 * self.mask(hidden)).float().view(b, 1, 9, f, f, h, w).softmax(dim=2)
        neigh = F.unfold(f * disp_low, kernel_size=3, padding=1).view(b, 1, 9, 1, 1, h, w)
        up = (mask * neigh).sum(dim=2)  # (B, 1, f, f, h, w)
        return up.permute(0, 1, 4, 2, 5, 3).reshape(b, 1, f * h, f * w).float()
