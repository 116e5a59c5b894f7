"""Iterative refinement blocks (paper Section III-B): the ConvGRU of eq. (GRU) and the Delta-D head."""

from __future__ import annotations

import torch
from torch import nn

from optstereo.models.layers import conv3x3


class ConvGRU(nn.Module):
    """Convolutional GRU exactly as the paper's eq. (GRU), with the static part of x^k factored out.

    z = sigmoid(Conv3x3([h, x], W_z)), r = sigmoid(Conv3x3([h, x], W_r)),
    h~ = tanh(Conv3x3([r * h, x], W_h)), h' = (1 - z) * h + z * h~.

    The paper's input is x^k = [D_s^{k-1}, M_l^k, F_l]. F_l does not change between iterations and a
    convolution is linear in its input channels, so Conv([h, D, M, F_l], W) = Conv([h, D, M], W_a) +
    Conv(F_l, W_b) with W = [W_a | W_b] split along input channels. ``precompute(F_l)`` evaluates the
    W_b part once per forward; ``forward`` adds it. The function is identical to the concatenated form
    (tests/test_model_parts.py checks it against a hand-written eq. with the re-assembled weights) and
    saves C = 256 of the ~420 input channels per iteration. W_b has no bias (W_a carries it).

    Shapes: h (B, hidden, H, W), x (B, input_dim, H, W), static (B, static_dim, H, W).
    """

    def __init__(self, hidden_dim: int, input_dim: int, static_dim: int = 0) -> None:
        super().__init__()
        self.hidden_dim = hidden_dim
        # W_z and W_r stacked in one conv (output channels [z | r]): one larger GEMM instead of two.
        self.convzr = conv3x3(hidden_dim + input_dim, 2 * hidden_dim)
        self.convq = conv3x3(hidden_dim + input_dim, hidden_dim)
        # One conv for the three static parts: (B, static_dim) -> (B, 3 * hidden) = [z | r | q].
        self.static = conv3x3(static_dim, 3 * hidden_dim, bias=False) if static_dim > 0 else None

    def precompute(self, static: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """Static contributions (c_z, c_r, c_q) of the iteration-invariant inputs, each (B, hidden, H, W)."""
        if self.static is None or static is None:
            return None
        cz, cr, cq = self.static(static).chunk(3, dim=1)
        return cz, cr, cq

    def forward(
        self,
        h: torch.Tensor,
        x: torch.Tensor,
        static: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
    ) -> torch.Tensor:
        zr = self.convzr(torch.cat([h, x], dim=1))
        if static is not None:
            zr = zr + torch.cat([static[0], static[1]], dim=1)
        z, r = torch.sigmoid(zr).chunk(2, dim=1)
        qc = self.convq(torch.cat([r * h, x], dim=1))
        if static is not None:
            qc = qc + static[2]
        q = torch.tanh(qc)
        return (1 - z) * h + z * q


class DispHead(nn.Module):
    """Two conv layers on h^k giving Delta D (1/8 pixel units): conv3x3 -> ReLU -> conv3x3 -> 1 channel."""

    def __init__(self, hidden_dim: int, head_dim: int = 128) -> None:
        super().__init__()
        self.conv1 = conv3x3(hidden_dim, head_dim)
        self.conv2 = conv3x3(head_dim, 1)
        self.relu = nn.ReLU(inplace=True)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return self.conv2(self.relu(self.conv1(h)))


class HiddenInit(nn.Module):
    """h^0 = tanh(Conv3x3(F_l)): the paper is silent on h^0; RAFT derives it from context features the
    same way, and OptStereo has no context network, so F_l itself is used."""

    def __init__(self, feature_dim: int, hidden_dim: int) -> None:
        super().__init__()
        self.conv = conv3x3(feature_dim, hidden_dim)

    def forward(self, feat_left: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.conv(feat_left))
