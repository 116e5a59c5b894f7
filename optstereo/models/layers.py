"""Small shared blocks: normalisation factory, conv helpers and the residual block of the extractor."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class InstanceNorm2d(nn.InstanceNorm2d):
    """``nn.InstanceNorm2d`` that keeps a channels-last image channels-last (the same state dict: none).

    For one image (B = 1) without affine parameters or running statistics, instance norm IS batch norm in training
    mode, and batch norm has channels-last kernels, while ``F.instance_norm`` first copies its input to NCHW. On
    CPUs whose oneDNN runs bf16 convolutions in NHWC (AMX), that copy and the one back to NHWC in the next
    convolution took ~30 % of a training step (docs/optstereo.md, "Channels-last encoder"). Every other input
    takes ``nn.InstanceNorm2d``'s path.

    Shapes: (B, C, H, W) -> (B, C, H, W), the input's memory format kept on the fast path.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if (x.dim() == 4 and x.shape[0] == 1 and not self.affine and not self.track_running_stats
                and x.is_contiguous(memory_format=torch.channels_last) and not x.is_contiguous()):
            return F.batch_norm(x, None, None, None, None, True, 0.0, self.eps)
        return super().forward(x)


def use_channels_last(x: torch.Tensor, *, exact_float32_grad: bool = False) -> bool:
    """Whether a CPU module should run ``x`` channels-last: eager CPU only (never while exporting or tracing).

    ``exact_float32_grad``: not for a full-precision forward in grad mode (no CPU autocast). The encoder asks for it
    because torch's channels-last batch-norm backward is less exact in float32 (gradients ~1 % off a float64
    reference on a tiny model, against 1e-5 for the NCHW path), which bf16 (~30 % off there) swamps but float32
    training should not get. Inference (no grad) and bf16 training take the channels-last path.
    """
    if x.device.type != "cpu" or x.dim() != 4:
        return False
    if torch.jit.is_tracing() or torch.onnx.is_in_onnx_export() or torch.compiler.is_compiling():
        return False
    if exact_float32_grad and torch.is_grad_enabled():
        return torch.is_autocast_enabled("cpu") or x.dtype in (torch.bfloat16, torch.float16)
    return True


def make_norm(kind: str, channels: int) -> nn.Module:
    """Normalisation layer by name.

    Args:
        kind: "instance" (RAFT's feature net; no affine, statistics per image so left and right are
            normalised independently), "batch", "group" (8 groups or fewer) or "none".
        channels: number of channels.
    """
    if kind == "instance":
        return InstanceNorm2d(channels)
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    if kind == "group":
        return nn.GroupNorm(num_groups=min(8, channels), num_channels=channels)
    if kind == "none":
        return nn.Identity()
    raise ValueError(f"unknown norm {kind!r}; expected instance, batch, group or none")


def conv3x3(in_channels: int, out_channels: int, stride: int = 1, bias: bool = True) -> nn.Conv2d:
    """3x3 convolution with 'same' padding (output = ceil(input / stride))."""
    return nn.Conv2d(in_channels, out_channels, kernel_size=3, stride=stride, padding=1, bias=bias)


class SeparableBlock(nn.Module):
    """Depthwise-separable residual block, no norm: relu(shortcut(x) + pw2(dw2(relu(pw1(dw1(x)))))).

    ``dw``: depthwise ``kernel`` x ``kernel`` convolutions (``dw1`` with ``stride``), ``pw``: 1x1 (``pw1`` from
    ``in_channels`` to ``out_channels``). ``shortcut``: the identity, or a strided 1x1 convolution when the block
    changes the channels or the resolution. The encoder's cheap stages (``ModelConfig.stage1 / stage2 =
    "separable"``): two of them cost about a quarter of two :class:`ResidualBlock` at 64 channels on a CPU (a
    depthwise 5x5 is memory-bound, a dense 3x3 compute-bound). ``pw2`` starts at zero, so a new block is
    relu(shortcut(x)): the identity on a non-negative input (the stem's ReLU output) when it has no 1x1 shortcut.

    Shapes: (B, in_channels, H, W) -> (B, out_channels, ceil(H / stride), ceil(W / stride)), float.
    """

    def __init__(self, in_channels: int, out_channels: int | None = None, *, kernel: int = 5, stride: int = 1) -> None:
        super().__init__()
        out_channels = in_channels if out_channels is None else out_channels
        pad = kernel // 2
        self.dw1 = nn.Conv2d(in_channels, in_channels, kernel, stride=stride, padding=pad, groups=in_channels)
        self.pw1 = nn.Conv2d(in_channels, out_channels, 1)
        self.dw2 = nn.Conv2d(out_channels, out_channels, kernel, padding=pad, groups=out_channels)
        self.pw2 = nn.Conv2d(out_channels, out_channels, 1)
        self.shortcut: nn.Module = (nn.Identity() if stride == 1 and in_channels == out_channels
                                    else nn.Conv2d(in_channels, out_channels, 1, stride=stride))
        nn.init.zeros_(self.pw2.weight)
        nn.init.zeros_(self.pw2.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = torch.relu(self.pw1(self.dw1(x)))
        return torch.relu(self.shortcut(x) + self.pw2(self.dw2(y)))


class ResidualBlock(nn.Module):
    """Two 3x3 conv-norm-ReLU layers with an identity (or strided 1x1) shortcut, as RAFT's fnet.

    Shapes: (B, in_channels, H, W) -> (B, out_channels, ceil(H / stride), ceil(W / stride)).
    """

    def __init__(self, in_channels: int, out_channels: int, *, stride: int = 1, norm: str = "instance") -> None:
        super().__init__()
        self.conv1 = conv3x3(in_channels, out_channels, stride=stride)
        self.norm1 = make_norm(norm, out_channels)
        self.conv2 = conv3x3(out_channels, out_channels)
        self.norm2 = make_norm(norm, out_channels)
        self.relu = nn.ReLU(inplace=True)
        self.shortcut: nn.Module
        if stride == 1 and in_channels == out_channels:
            self.shortcut = nn.Identity()
        else:
            self.shortcut = nn.Sequential(
                nn.Conv2d(in_channels, out_channels, kernel_size=1, stride=stride), make_norm(norm, out_channels)
            )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.relu(self.norm1(self.conv1(x)))
        y = self.relu(self.norm2(self.conv2(y)))
        return self.relu(self.shortcut(x) + y)
