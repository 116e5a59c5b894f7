"""InputPadder: pad (..., H, W) tensors to a multiple of the network stride and crop predictions back.

KITTI frames are 375 x 1242 (and 370 x 1224, 376 x 1241); OptStereo needs H, W divisible by 8. Each network class
states its multiple as a class attribute ``divisor`` (OptStereo 8, HITNet 8: its finest tiles); ``divisor_of(model)``
reads it, so inference pads for whichever network a checkpoint holds.
Padding is split evenly between the two sides (the extra pixel, if odd, goes bottom/right) with
edge replication. Padding both views by the same columns shifts left and right equally, so
disparities are unchanged; ``unpad`` only crops.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

DEFAULT_DIVISOR = 8  # OptStereo's 1/8 features; used for a model that does not state its divisor


def divisor_of(model: nn.Module) -> int:
    """The multiple a model needs H and W to be: its ``divisor`` attribute (DDP/compile wrappers unwrapped), else 8."""
    for wrapper_attr in ("module", "_orig_mod"):
        inner = getattr(model, wrapper_attr, None)
        if isinstance(inner, nn.Module):
            return divisor_of(inner)
    return int(getattr(model, "divisor", DEFAULT_DIVISOR))


class InputPadder:
    """Pads to a multiple of ``divis_by``.

    Args:
        shape: shape of the tensors to pad, (..., H, W) (e.g. ``left.shape``).
        divis_by: required divisor of the padded H and W.
        mode: torch.nn.functional.pad mode ("replicate", "reflect" or "constant").
    """

    def __init__(self, shape: Sequence[int], divis_by: int = 8, mode: str = "replicate") -> None:
        if len(shape) < 2:
            raise ValueError(f"InputPadder needs a shape (..., H, W), got {tuple(shape)}")
        if divis_by < 1:
            raise ValueError(f"divis_by must be >= 1, got {divis_by}")
        self.height, self.width = int(shape[-2]), int(shape[-1])
        self.divis_by = divis_by
        self.mode = mode
        pad_h = (-self.height) % divis_by
        pad_w = (-self.width) % divis_by
        # (left, right, top, bottom) in F.pad order.
        self.pads = (pad_w // 2, pad_w - pad_w // 2, pad_h // 2, pad_h - pad_h // 2)

    @property
    def padded_shape(self) -> tuple[int, int]:
        """(H, W) after padding."""
        left, right, top, bottom = self.pads
        return self.height + top + bottom, self.width + left + right

    def pad(self, *tensors: torch.Tensor) -> list[torch.Tensor]:
        """Pad each (B, C, H, W) tensor; returns a list in the same order."""
        out = []
        for t in tensors:
            if tuple(t.shape[-2:]) != (self.height, self.width):
                raise ValueError(
                    f"InputPadder was built for (H, W) = ({self.height}, {self.width}), got {tuple(t.shape)}"
                )
            if not any(self.pads):
                out.append(t)
            elif t.ndim == 4 or self.mode == "constant":
                out.append(F.pad(t, self.pads, mode=self.mode))
            else:
                # replicate/reflect need a batch dim and a channel dim: add them and remove them again.
                lead = t.shape[:-2]
                flat = t.reshape(-1, 1, self.height, self.width)
                out.append(F.pad(flat, self.pads, mode=self.mode).reshape(*lead, *self.padded_shape))
        return out

    def unpad(self, t: torch.Tensor) -> torch.Tensor:
        """Crop a padded (..., H_pad, W_pad) tensor back to (..., H, W)."""
        hp, wp = self.padded_shape
        if tuple(t.shape[-2:]) != (hp, wp):
            raise ValueError(f"unpad expects (..., {hp}, {wp}), got {tuple(t.shape)}")
        left, _, top, _ = self.pads
        return t[..., top : top + self.height, left : left + self.width]
