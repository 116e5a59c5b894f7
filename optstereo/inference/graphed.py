"""The default one-pass inference of a fixed (H, W) as one CUDA graph: uint8 pair in, disparity out (issue 52).

:class:`GraphedPass` holds static buffers for one input size and runs, on the device, what
``optstereo.inference.engine.run`` does for a plain one-pass config at input scale 1: the uint8 -> float batch of
``to_batch``, the padding (``InputPadder``), the network in test mode (with the caller's autocast) and the unpadding.
On CUDA the whole of it is captured once as a ``torch.cuda.CUDAGraph`` and each call replays it: no Python, no kernel
launches, no allocations per frame. On the CPU the same static-buffer pipeline runs eagerly, so tests/test_graphed.py
holds it equal to ``infer`` on machines without a GPU.

Only configs whose pass does not depend on the data can be captured: ``coarse_start``, ``select`` and a post-filter
(``refine``) are refused by name; the adaptive second pass (``adaptive_ref_disp``) only where it can never run at
this size (its pixel bound keeps the factor below ``ADAPTIVE_MIN_GAIN``: every KITTI size for the shipped model).
A resize (``scale`` != 1) is refused: on an H200 (2026-11-27) a device-side resize at scale 0.5 differed from
``infer``'s OpenCV resize by 0.23 px, and the shipped default runs KITTI frames at scale 1.
"""

from __future__ import annotations

import contextlib
import math

import numpy as np
import numpy.typing as npt
import torch
from torch import nn

from optstereo.choices import AmpMode
from optstereo.inference.config import InferenceConfig
from optstereo.inference.engine import first_scale, inference_autocast, model_inference_config
from optstereo.inference.padding import InputPadder, divisor_of
from optstereo.inference.rescale import ADAPTIVE_MIN_GAIN

__all__ = ["GraphedPass", "check_capturable"]

WARMUP_CALLS = 3  # eager calls on a side stream before capture (cuDNN/cuBLAS workspaces, lazy inits)


class GraphedPass:
    """One plain network pass of a fixed input size, captured as a CUDA graph on CUDA (eager on the CPU).

    ``GraphedPass(model, (375, 1242), device="cuda", amp="bf16", scale=1.0)(left, right)`` equals
    ``infer(model, left, right, device="cuda", amp="bf16", scale=1.0)`` (float32: to TF32/kernel rounding) for every
    pair of that size, without the per-frame launches and allocations. The graph reads the model's parameters in
    place: a changed state dict is seen, a model moved to another device is not (build a new one).

    Args:
        model: OptStereo-like (test_mode=True returns (low, full)); whatever ``optstereo.api.load_model`` gives.
        shape: (H, W) of every input pair.
        device: where it runs; CUDA captures a graph, the CPU runs the same pipeline eagerly.
        iters: GRU iterations (None = the model's InferenceConfig, else its default).
        scale: input scale (None = the model's ``InferenceConfig.scale``; given, the adaptive pass is off, as in
            ``infer``); only 1 is captured.
        amp: ``none`` (float32), ``bf16`` or ``fp16`` (CUDA), as ``infer``.

    Raises:
        ValueError: a config it cannot capture (naming the setting), a bad shape or amp.
    """

    def __init__(self, model: nn.Module, shape: tuple[int, int], *, device: torch.device | str = "cuda",
                 iters: int | None = None, scale: float | None = None, amp: AmpMode = "none") -> None:
        self.model = model
        self.height, self.width = (int(v) for v in shape)
        self.device = torch.device(device)
        param = next(model.parameters(), None)
        if param is not None and param.device.type != self.device.type:
            raise ValueError(f"the model's parameters are on {param.device}, GraphedPass was asked for {self.device}: "
                             "move the model first")
        self.amp = amp
        inference_autocast(amp, self.device)  # validates amp (fp16 needs CUDA) and warns on emulated CPU bf16
        self.config = model_inference_config(model, iters, scale)
        check_capturable(self.config, (self.height, self.width))
        self.padder = InputPadder((self.height, self.width), divis_by=divisor_of(model))
        self.graph: torch.cuda.CUDAGraph | None = None
        pin = self.device.type == "cuda"
        self._pair = torch.zeros((2, self.height, self.width, 3), dtype=torch.uint8, device=self.device)
        self._host_pair = torch.zeros((2, self.height, self.width, 3), dtype=torch.uint8, pin_memory=pin)
        self._host_out = torch.zeros((self.height, self.width), dtype=torch.float32, pin_memory=pin)
        self._out: torch.Tensor | None = None
        if self.device.type == "cuda":
            self._capture()

    @torch.inference_mode()
    def _pipeline(self) -> torch.Tensor:
        """Static uint8 pair -> (H, W) float32 disparity, all on the device, no host syncs (capturable)."""
        pair = self._pair.permute(0, 3, 1, 2).contiguous().float()  # (2, 3, H, W), as to_batch
        left, right = self.padder.pad(pair[:1], pair[1:])
        was_training = self.model.training
        self.model.eval()
        try:
            with self._autocast():
                _, full = self.model(left, right, iters=self.config.iters, test_mode=True)
        finally:
            self.model.train(was_training)
        # the unpadded view copied inside the graph: the copy out needs no staging tensor
        return self.padder.unpad(full)[0, 0].float().contiguous()

    def _autocast(self) -> contextlib.AbstractContextManager:
        """Autocast as ``inference_autocast`` on the CPU; on CUDA without its weight-cast cache, whose tensors are
        freed when the context exits and so must not be read by a graph (the casts are then part of the graph)."""
        if self.amp == "none" or self.device.type != "cuda":
            return inference_autocast(self.amp, self.device)
        dtype = torch.bfloat16 if self.amp == "bf16" else torch.float16
        return torch.autocast("cuda", dtype=dtype, cache_enabled=False)

    def _capture(self) -> None:
        """Warm up on a side stream, then capture the pipeline into ``self.graph`` (its own memory pool)."""
        side = torch.cuda.Stream(self.device)
        side.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.device(self.device), torch.cuda.stream(side):
            for _ in range(WARMUP_CALLS):
                self._pipeline()
        torch.cuda.current_stream(self.device).wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.device(self.device), torch.cuda.graph(graph):
            self._out = self._pipeline()
        self.graph = graph

    def __call__(self, left: npt.NDArray[np.uint8], right: npt.NDArray[np.uint8]) -> npt.NDArray[np.float32]:
        """(H, W, 3) uint8 RGB pair of the built shape -> (H, W) float32 disparity in the input's pixels (a new
        array: the next call does not change it)."""
        expected = (self.height, self.width, 3)
        for name, image in (("left", left), ("right", right)):
            if image.shape != expected or image.dtype != np.uint8:
                raise ValueError(f"GraphedPass was built for {name} of shape {expected} uint8, got "
                                 f"{image.shape} {image.dtype}")
        host = self._host_pair.numpy()
        host[0], host[1] = left, right
        self._pair.copy_(self._host_pair, non_blocking=True)
        if self.graph is None:
            out = self._pipeline()
        else:
            self.graph.replay()
            out = self._out
        self._host_out.copy_(out, non_blocking=True)
        if self.device.type == "cuda":
            torch.cuda.current_stream(self.device).synchronize()
        return self._host_out.numpy().copy()


def check_capturable(config: InferenceConfig, shape: tuple[int, int]) -> None:
    """Raise ValueError naming the setting unless ``config`` makes one zero-start pass at input scale 1 on an (H, W)
    pair whatever its content: no resize (nor a pixel-budget enlargement), no coarse start (so no selection), no
    post-filter, and an adaptive pass only where its pixel bound keeps it from ever running
    (``optstereo.inference.rescale.adaptive_factor``)."""
    config.validate()
    if config.scale != 1.0:
        raise ValueError(f"GraphedPass captures input scale 1 only (scale={config.scale}): a device-side resize "
                         "disagreed with infer's on a GPU; use infer, or scale=1")
    if config.coarse_start:
        raise ValueError(f"GraphedPass runs one zero-start pass: coarse_start=True (select={config.select}) needs "
                         "more passes, use infer")
    if config.refine != "none":
        raise ValueError(f"GraphedPass runs no post-filter: refine={config.refine!r} is not captured, use infer "
                         "or refine='none'")
    if (first := first_scale(config, shape)) != 1.0:
        raise ValueError(f"GraphedPass captures input scale 1 only: a {shape[0]}x{shape[1]} pair is resized "
                         f"{first:.3f}x toward the pixel budget (enlarge_max="
                         f"{config.enlarge_max}, shrink_large={config.shrink_large}); give scale= (turns it off, as "
                         "infer does) or use infer")
    if config.adaptive:
        h, w = shape
        bound = math.sqrt(config.adaptive_ref_pixels / (h * w))
        if bound >= ADAPTIVE_MIN_GAIN:
            raise ValueError(f"GraphedPass cannot capture the adaptive pass (adaptive_ref_disp="
                             f"{config.adaptive_ref_disp}): a {h}x{w} pair may be enlarged up to {bound:.3f}x "
                             "depending on its disparities; give scale= (turns it off, as infer does) or use infer")
