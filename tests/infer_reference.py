"""The inference path as it was before ``InferenceConfig`` (optstereo 0.1.0 up to issue 42), kept as a reference:
``optstereo.inference.engine.run`` must give the same disparities for the sequences it kept, and the coarse start's
change
(the training's ``optstereo.inference.cascade.coarse_start`` on the resized, padded pair instead of a second resize of
the
input to half the scale) is measured against it. Copied from the old ``rescale.scaled_passes`` and
``inference._network``; not used by the product."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from optstereo.inference.cascade import grid_start, jump_limit, photometric_select
from optstereo.inference.engine import apply_refine, to_batch
from optstereo.inference.padding import InputPadder, divisor_of
from optstereo.inference.rescale import adaptive_factor, disparity_to_size, rescaled_pair


@torch.inference_mode()
def old_network(model: nn.Module, left: np.ndarray, right: np.ndarray, start: np.ndarray | None,
                iters: int | None = None) -> np.ndarray:
    """One pass on the pair as given, started from ``start`` ((H, W) disparity of the pair) or zero."""
    model.eval()
    left_t, right_t = to_batch(left, torch.device("cpu")), to_batch(right, torch.device("cpu"))
    padder = InputPadder(left_t.shape, divis_by=divisor_of(model))
    left_t, right_t = padder.pad(left_t, right_t)
    extra = {}
    if start is not None:
        start_t = torch.from_numpy(np.ascontiguousarray(start, np.float32))[None, None]
        extra["disp_init"] = grid_start(padder.pad(start_t)[0])
    _, full = model(left_t, right_t, iters=iters, test_mode=True, **extra)
    return padder.unpad(full)[0, 0].float().numpy().astype(np.float32)


def old_at_scale(model: nn.Module, left: np.ndarray, right: np.ndarray, scale: float,
                 start: np.ndarray | None = None, iters: int | None = None) -> np.ndarray:
    if scale == 1.0:
        return old_network(model, left, right, start, iters)
    left_s, right_s = rescaled_pair(left, right, scale)
    start_s = None if start is None else disparity_to_size(start, left_s.shape[:2])
    return disparity_to_size(old_network(model, left_s, right_s, start_s, iters), left.shape[:2])


def old_infer(model: nn.Module, left: np.ndarray, right: np.ndarray, scale: float = 1.0, refine: str = "none",
              refs: tuple[float, int] | None = None, cascade: bool = False, select: bool = False,
              select_jump: float = 0.0, iters: int | None = None) -> tuple[np.ndarray, float]:
    """(disparity, final scale) of the old ``infer_scaled`` with the old ModelConfig settings given explicitly."""
    disp = old_at_scale(model, left, right, scale, iters=iters)
    if refs is not None:
        gain = adaptive_factor(disp, *refs)
        if gain > 1.0:
            scale *= gain
            disp = old_at_scale(model, left, right, scale, iters=iters)
    if cascade:
        zero = disp
        coarse = old_at_scale(model, left, right, scale / 2, iters=iters)
        disp = old_at_scale(model, left, right, scale, start=coarse, iters=iters)
        if select:
            disp = photometric_select(left, right, (disp, zero), max_jump=jump_limit(left.shape[1], select_jump))
    return apply_refine(disp, left, refine), scale
