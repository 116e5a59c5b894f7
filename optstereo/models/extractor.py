"""Feature extraction of OptStereo (paper Section III-B): one residual network, shared by both views."""

from __future__ import annotations

import torch
from torch import nn

from optstereo.models.layers import ResidualBlock, SeparableBlock, make_norm, use_channels_last


def make_stage(name: str, kind: str, in_channels: int, out_channels: int, *, stride: int,
               norm: str = "instance") -> nn.Sequential:
    """One encoder stage of two blocks, the first with ``stride`` (and ``in_channels`` -> ``out_channels``):
    ``kind`` "residual" = RAFT's :class:`ResidualBlock` pair, "separable" = a :class:`SeparableBlock` pair (no norm).
    ``name`` (``stage1`` / ``stage2``) names the option in the error for an unknown ``kind``."""
    if kind == "separable":
        return nn.Sequential(SeparableBlock(in_channels, out_channels, stride=stride), SeparableBlock(out_channels))
    if kind == "residual":
        return nn.Sequential(ResidualBlock(in_channels, out_channels, stride=stride, norm=norm),
                             ResidualBlock(out_channels, out_channels, norm=norm))
    raise ValueError(f"{name} must be 'residual' or 'separable', got {kind!r}")


class FeatureEncoder(nn.Module):
    """Residual feature network: 7x7 stem, six residual blocks (two each at 1/2, 1/4, 1/8), 1x1 projection.

    This is the layout of RAFT's "basic encoder" that the paper's figure draws: stem (stride 2) ->
    2 blocks at 1/2 (64 ch) -> 2 blocks at 1/4 (96 ch) -> 2 blocks at 1/8 (128 ch) -> 1x1 conv to C.
    ``stage1 = "separable"`` makes the two blocks at 1/2 :class:`SeparableBlock` (about a sixth of the CPU pass
    saved), ``stage2 = "separable"`` the two at 1/4 (the first strided, 64 -> 96, with a 1x1 shortcut).
    Both views go through the same module in ONE call (concatenated along the batch), which is how the
    weights are shared; instance norm keeps the statistics of the two views separate.

    Shapes: (B, 3, H, W) float (normalised to [-1, 1]) -> (B, C, H / 8, W / 8) float.
    """

    def __init__(self, output_dim: int = 256, *, norm: str = "instance", widths: tuple[int, int, int] = (64, 96, 128),
                 stage1: str = "residual", stage2: str = "residual"):
        super().__init__()
        w1, w2, w3 = widths
        self.stem = nn.Sequential(
            nn.Conv2d(3, w1, kernel_size=7, stride=2, padding=3), make_norm(norm, w1), nn.ReLU(inplace=True)
        )
        self.layer1 = make_stage("stage1", stage1, w1, w1, stride=1, norm=norm)
        self.layer2 = make_stage("stage2", stage2, w1, w2, stride=2, norm=norm)
        self.layer3 = make_stage("stage3", "residual", w2, w3, stride=2, norm=norm)
        self.proj = nn.Conv2d(w3, output_dim, kernel_size=1)
        self.output_dim = output_dim
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                # Same init as RAFT's encoders (kaiming fan-out for ReLU networks).
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
            elif isinstance(m, (nn.BatchNorm2d, nn.GroupNorm)):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)
        for m in self.modules():
            if isinstance(m, SeparableBlock):  # its identity (or shortcut-only) start: the loop above re-drew pw2
                nn.init.zeros_(m.pw2.weight)
                nn.init.zeros_(m.pw2.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if use_channels_last(x, exact_float32_grad=True):
            # oneDNN convolves NHWC on CPU; an NCHW tensor between layers costs two layout copies per bf16 conv
            # (docs/optstereo.md, "Channels-last encoder"). Same values; the output goes back to NCHW.
            return self._forward(x.contiguous(memory_format=torch.channels_last)).contiguous()
        return self._forward(x)

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.stem(x)
        x = self.layer1(x)
        x = self.layer2(x)
        x = self.layer3(x)
        return self.proj(x)
