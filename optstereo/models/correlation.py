"""1-D correlation pyramid and its lookup (paper Section III-B, "cost volume" and "lookup").

M0(i, j, k) = sum_h F_l(i, j, h) F_r(i, k, h) / sqrt(C) for every pair of columns j, k of the same
row i, at 1/8 resolution. M1..M_{L-1} average-pool the LAST dimension (k) by 2 each, so M^k has
floor(W / 2^k) entries (an odd trailing column is dropped, as avg_pool does). The 1/sqrt(C) scale is
beyond the paper; it only keeps M0 O(1) so the GRU input is the same size whatever C is.

Lookup: for the current disparity D_s (1/8 pixel units, positive: left(x) matches right(x - d)) the
pixel (i, j) looks at j' = j - D_s(i, j). Level k is sampled at the real positions j'/2^k + dj,
|dj| <= d, with linear interpolation; taps outside [0, W_k - 1] read zero (so a position half a
column outside the row still gets half of the border value, exactly like linear interpolation of a
zero-padded row). The result has levels x (2d + 1) channels ordered level-major, offset-minor.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn


def correlation_volume(feat_left: torch.Tensor, feat_right: torch.Tensor, *, scale: bool = True) -> torch.Tensor:
    """All-pairs correlation along rows, in float32.

    Args:
        feat_left, feat_right: (B, C, H, W) float features F_l, F_r.
        scale: divide by sqrt(C).

    Returns:
        (B, H, W, W) float32 volume M0; M0[b, i, j, k] = <F_l[b, :, i, j], F_r[b, :, i, k]> (/ sqrt(C)).
    """
    # Disable autocast: a dot product over C = 256 channels in fp16/bf16 loses too many bits.
    with torch.autocast(device_type=feat_left.device.type, enabled=False):
        fl = feat_left.float().permute(0, 2, 3, 1)  # (B, H, W, C)
        fr = feat_right.float().permute(0, 2, 1, 3)  # (B, H, C, W)
        vol = torch.matmul(fl, fr)  # batched over (B, H): (W, C) @ (C, W)
        if scale:
            vol = vol / math.sqrt(feat_left.shape[1])
    return vol


def build_pyramid(volume: torch.Tensor, num_levels: int) -> list[torch.Tensor]:
    """Average-pool the last dimension of M0 by 2, num_levels - 1 times.

    Args:
        volume: (B, H, W, W) float32 M0.
        num_levels: L >= 1.

    Returns:
        [M0, M1, ..., M_{L-1}], M^k of shape (B, H, W, floor(W / 2^k)).
    """
    b, h, w, w2 = volume.shape
    pyramid = [volume]
    for _ in range(num_levels - 1):
        last = pyramid[-1]
        pooled = F.avg_pool1d(last.reshape(b * h * w, 1, last.shape[-1]), kernel_size=2, stride=2)
        pyramid.append(pooled.reshape(b, h, w, -1))
    return pyramid


def lookup_pyramid(pyramid: list[torch.Tensor], disp: torch.Tensor, radius: int) -> torch.Tensor:
    """Sample every level around j' = j - D at 2d + 1 taps with linear interpolation (zero outside).

    Args:
        pyramid: levels (B, H, W, W_k) float32, from build_pyramid.
        disp: (B, 1, H, W) float disparity D_s at 1/8 resolution (1/8 pixel units).
        radius: d.

    Returns:
        (B, L * (2d + 1), H, W) float32 M_l; channel k * (2d + 1) + (dj + d) holds level k, offset dj.
    """
    b, _, h, w = disp.shape
    with torch.autocast(device_type=disp.device.type, enabled=False):
        cols = torch.arange(w, device=disp.device, dtype=torch.float32).view(1, 1, w)
        target = cols - disp[:, 0].float()  # (B, H, W): j' = j - D
        offsets = torch.arange(-radius, radius + 1, device=disp.device, dtype=torch.float32)
        out = []
        for level, vol in enumerate(pyramid):
            width = vol.shape[-1]
            pos = target.unsqueeze(-1) / (2**level) + offsets  # (B, H, W, 2d + 1), real indices
            x0f = torch.floor(pos)
            frac = pos - x0f
            x0 = x0f.long()
            x1 = x0 + 1
            v0 = torch.gather(vol, 3, x0.clamp(0, width - 1)) * ((x0 >= 0) & (x0 < width))
            v1 = torch.gather(vol, 3, x1.clamp(0, width - 1)) * ((x1 >= 0) & (x1 < width))
            out.append(v0 * (1.0 - frac) + v1 * frac)
        sampled = torch.cat(out, dim=3)  # (B, H, W, L * (2d + 1))
    return sampled.permute(0, 3, 1, 2).contiguous()


class CorrBlock1D(nn.Module):
    """Correlation pyramid builder + lookup with a fixed number of levels and radius (no parameters).

    Use ``pyramid = block.build_pyramid(F_l, F_r)`` once per forward and ``block.lookup(pyramid, D_s)``
    at every iteration. ``out_channels`` = levels x (2d + 1).
    """

    def __init__(self, num_levels: int = 4, radius: int = 4, *, scale: bool = True) -> None:
        super().__init__()
        if num_levels < 1 or radius < 0:
            raise ValueError(f"CorrBlock1D needs num_levels >= 1 and radius >= 0, got {num_levels}, {radius}")
        self.num_levels = num_levels
        self.radius = radius
        self.scale = scale

    @property
    def out_channels(self) -> int:
        return self.num_levels * (2 * self.radius + 1)

    @property
    def min_width(self) -> int:
        """Smallest 1/8 width that leaves at least one entry in the coarsest level."""
        return 2 ** (self.num_levels - 1)

    def build_pyramid(self, feat_left: torch.Tensor, feat_right: torch.Tensor) -> list[torch.Tensor]:
        """(B, C, H, W) features -> list of L volumes (B, H, W, W_k) float32."""
        return build_pyramid(correlation_volume(feat_left, feat_right, scale=self.scale), self.num_levels)

    def lookup(self, pyramid: list[torch.Tensor], disp: torch.Tensor) -> torch.Tensor:
        """(B, 1, H, W) disparity -> (B, out_channels, H, W) float32 sampled costs."""
        return lookup_pyramid(pyramid, disp, self.radius)

    def extra_repr(self) -> str:
        return f"num_levels={self.num_levels}, radius={self.radius}, scale={self.scale}"
