"""The Python API: ``load_model`` and ``predict``, the same calls the CLIs make.

    from optstereo import load_model, predict
    model = load_model("pretrained")                 # or a checkpoint file / run directory
    disp = predict(model, left, right)               # (H, W, 3) uint8 RGB each -> (H, W) float32 px
    disps = predict(model, [(l1, r1), (l2, r2)])     # a list of pairs -> a list of maps (any sizes)
    disp, conf = predict(model, left, right, confidence=True)  # + (H, W) float32 confidence in [0, 1]
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from torch import nn

from optstereo.checkpoint import build_model_from_checkpoint
from optstereo.distributed import resolve_device
from optstereo.inference.confidence import infer_with_confidence
from optstereo.inference.engine import infer
from optstereo.inference.fastpath import engineer
from optstereo.pretrained import resolve_checkpoint_spec
from pvm_labeler.common.configtools import plain_scalar

Image = npt.NDArray[np.uint8]


def load_model(checkpoint: str | Path = "pretrained", device: str | torch.device = "cpu") -> nn.Module:
    """Build the model a checkpoint records and load its weights (eval mode, on ``device``), prepared for inference
    (``optstereo.inference.fastpath.engineer``: the same parameters and state dict, a faster CPU pass).

    Args:
        checkpoint: ``"pretrained"`` (the shipped model), a .pt/.safetensors file or a training RUN_DIR.
        device: ``"cpu"``, ``"cuda"``, ``"auto"`` (cuda when available) or a torch.device.
    """
    dev = resolve_device(device) if isinstance(device, str) else device
    return engineer(build_model_from_checkpoint(resolve_checkpoint_spec(checkpoint), dev))


def _device_of(model: nn.Module) -> torch.device:
    return next(model.parameters()).device


def predict(
    model: nn.Module,
    left: Image | Sequence[tuple[Image, Image]],
    right: Image | None = None,
    *,
    iters: int | None = None,
    amp: str = "none",
    scale: float | None = None,
    confidence: bool = False,
) -> Any:
    """Disparity of the left view: positive, full resolution, left(x) matches right(x - d).

    Args:
        model: from :func:`load_model`.
        left, right: (H, W, 3) uint8 RGB arrays of one pair (any H, W: padded to a multiple of 8 inside); or
            ``left`` a list of (left, right) pairs and ``right`` None.
        iters: GRU iterations (None = the model's own).
        amp: ``none``, ``bf16`` or ``fp16`` (CUDA).
        scale: run the network on both images resized by this factor (e.g. 0.5 for a large Middlebury pair); the
            disparity comes back at the input's size, in its pixels. None = the model's own
            (``model.inference_config``, the InferenceConfig its checkpoint records: optstereo.inference.engine.run).
        confidence: also return each map's confidence in [0, 1] (``optstereo.inference.confidence``: photometric x LR,
            one more network pass).

    Returns:
        (H, W) float32, or a list of them for a list of pairs (each at its own size); with ``confidence`` a
        (disparity, confidence) tuple in place of each map.
    """
    device = _device_of(model)
    iters, scale = plain_scalar(iters), plain_scalar(scale)  # np.int64(2) was refused

    def one(lft: Image, rgt: Image) -> Any:
        if confidence:
            return infer_with_confidence(model, lft, rgt, iters=iters, device=device, amp=amp, scale=scale)
        return infer(model, lft, rgt, iters=iters, device=device, amp=amp, scale=scale)

    if right is None:
        return [one(np.asarray(lft), np.asarray(rgt)) for lft, rgt in _pairs_of(left)]
    return one(np.asarray(left), np.asarray(right))


def _pairs_of(pairs: Any) -> list[tuple[Any, Any]]:
    """``predict``'s list of (left, right) pairs, checked: ValueError naming what was given instead (an image, one
    pair as a tuple or list, an item that is no pair)."""
    if hasattr(pairs, "ndim"):
        raise ValueError("predict(model, left, right): give the right image, or a list of (left, right) pairs")
    if isinstance(pairs, tuple | list) and len(pairs) == 2 and all(getattr(x, "ndim", 0) == 3 for x in pairs):
        raise ValueError(f"predict(model, {'(left, right)' if isinstance(pairs, tuple) else '[left, right]'}): one "
                         "pair is predict(model, left, right) (or predict(model, *pair)); several are a list of "
                         "(left, right) tuples")
    if not isinstance(pairs, Sequence) or isinstance(pairs, str):
        raise ValueError(f"predict(model, pairs): pairs must be a list of (left, right) tuples, got "
                         f"{type(pairs).__name__}")
    for i, item in enumerate(pairs):
        if not isinstance(item, tuple | list) or len(item) != 2:
            got = f"a {type(item).__name__}" + (f" of {len(item)} items" if isinstance(item, tuple | list) else "")
            raise ValueError(f"predict(model, pairs): item {i} must be a (left, right) tuple, got {got}")
    return list(pairs)
