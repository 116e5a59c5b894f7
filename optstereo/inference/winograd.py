"""Winograd F(4x4, 3x3) convolution for the GRU's 3x3 convolutions on the CPU (stride 1, padding 1, float32).

A 3x3 convolution over 4x4 output tiles costs 36 multiplies per tile and channel pair in the Winograd domain
instead of 144 (Lavin & Gray, "Fast Algorithms for Convolutional Neural Networks", CVPR 2016, F(4x4, 3x3)): the
input tiles (6x6, overlapping by 2) and the weights are transformed (V = B^T d B, U = G g G^T), multiplied channel-
wise as 36 matrix products (V_ij @ U_ij over the input channels), and the products transformed back (Y = A^T M A).
The transforms are separable matrix products over the 6 tile rows, then the 6 tile columns. At the GRU's size (165
or 128 input channels at 1/8 of a KITTI frame) the 36 products plus the transforms take about 60 % of oneDNN's
direct convolution on an AVX2 CPU; for the encoder's wide layers (64-96 channels at 1/2-1/4) the transforms'
memory traffic costs more than the products save, so they stay direct.

The weights' transform runs in float64 and is cast once; the result differs from the direct convolution by float32
rounding of the transforms (about 1e-4 absolute on O(1) outputs, 1e-5 for the direct one).

References:
    A. Lavin, S. Gray. Fast Algorithms for Convolutional Neural Networks. CVPR 2016 (the matrices B^T, G, A^T).
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F

TILE = 4  # output tile m; input tile m + r - 1 = 6
SIDE = TILE + 2
# Interpolation points 0, -1, 1, -2, 2 and infinity.
B_T = torch.tensor([[4, 0, -5, 0, 1, 0], [0, -4, -4, 1, 1, 0], [0, 4, -4, -1, 1, 0], [0, -2, -1, 2, 1, 0],
                    [0, 2, -1, -2, 1, 0], [0, 4, 0, -5, 0, 1]], dtype=torch.float64)
G = torch.tensor([[1 / 4, 0, 0], [-1 / 6, -1 / 6, -1 / 6], [-1 / 6, 1 / 6, -1 / 6], [1 / 24, 1 / 12, 1 / 6],
                  [1 / 24, -1 / 12, 1 / 6], [0, 0, 1]], dtype=torch.float64)
A_T = torch.tensor([[1, 1, 1, 1, 1, 0], [0, 1, -1, 2, -2, 0], [0, 1, 1, 4, 4, 0], [0, 1, -1, 8, -8, 1]],
                   dtype=torch.float64)
# A^T's column 1 is all ones, so a constant added to M[1, 1] reaches each of the 16 outputs of a tile exactly once.
BIAS_SLOT = 1 * SIDE + 1


@functools.cache
def _transforms(device: torch.device, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """(B^T, A^T) on ``device`` in ``dtype``, made once (not per call), as normal tensors even when first asked for
    under inference mode (an inference tensor could not be saved for a later backward)."""
    with torch.inference_mode(False):
        return B_T.to(device=device, dtype=dtype), A_T.to(device=device, dtype=dtype)


def winograd_weight(weight: torch.Tensor) -> torch.Tensor:
    """U = G g G^T of a (C_out, C_in, 3, 3) weight -> (36, C_in, C_out) float32, computed in float64."""
    if weight.shape[-2:] != (3, 3):
        raise ValueError(f"Winograd F(4x4, 3x3) needs a 3x3 kernel, got {tuple(weight.shape)}")
    g = G.to(weight.device)
    u = torch.einsum("ik,ockl,jl->ijco", g, weight.detach().double(), g)
    return u.reshape(SIDE * SIDE, weight.shape[1], weight.shape[0]).float().contiguous()


def winograd_conv3x3(x: torch.Tensor, u: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    """``F.conv2d(x, weight, bias, padding=1)`` for one image with U = winograd_weight(weight).

    Args:
        x: (1, C_in, H, W) float32, best channels-last (its (H, W, C) view is then free).
        u: (36, C_in, C_out) from :func:`winograd_weight`.
        bias: (C_out,) or None.

    Returns:
        (1, C_out, H, W) float32, channels-last (contiguous when W is a multiple of 4).
    """
    b, c, h, w = x.shape
    if b != 1 or u.shape[1] != c:
        raise ValueError(f"winograd_conv3x3 takes one image of {u.shape[1]} channels, got {tuple(x.shape)}")
    th, tw = -(-h // TILE), -(-w // TILE)
    # Zero padding: 1 before, and after it up to whole tiles (outputs past H, W are cut off below).
    padded = F.pad(x.permute(0, 2, 3, 1), (0, 0, 1, tw * TILE + 1 - w, 1, th * TILE + 1 - h))[0]
    s = padded.stride()
    tiles = padded.as_strided((SIDE, SIDE, th, tw, c), (s[0], s[1], TILE * s[0], TILE * s[1], s[2]))
    b_t, a_t = _transforms(x.device, x.dtype)
    v = torch.mm(b_t, tiles.reshape(SIDE, -1)).view(SIDE, SIDE, -1)  # tile rows (reshape gathers the tiles)
    v = torch.matmul(b_t, v).view(SIDE * SIDE, th * tw, c)  # tile columns
    m = torch.bmm(v, u)  # (36, tiles, C_out)
    c_out = u.shape[-1]
    if bias is not None:
        m[BIAS_SLOT].add_(bias)
    y = torch.mm(a_t, m.view(SIDE, -1)).view(TILE, SIDE, -1)
    y = torch.matmul(a_t, y).view(TILE, TILE, th, tw, c_out)
    out = y.permute(2, 0, 3, 1, 4).reshape(th * TILE, tw * TILE, c_out)[:h, :w]
    return out.unsqueeze(0).permute(0, 3, 1, 2)
