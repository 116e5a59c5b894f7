"""The one inference path: a network and an ``InferenceConfig`` -> the disparity of a pair (``run``).

``run`` resizes the pair once by ``InferenceConfig.scale``, pads it to the network's multiple, runs the network
pass(es) in order, unpads, brings the disparity back to the input's size and pixels, and applies the post-filter.
The passes: the zero-start one; with ``adaptive_ref_disp`` set, the same again on a small pair enlarged by
``optstereo.inference.rescale.adaptive_factor``; with ``coarse_start`` the final pass starts its GRU from
``optstereo.inference.cascade.coarse_start`` (the training's own function: a pass on the padded pair at half size), and
with
``select`` per pixel the better matching of it and the zero-start pass is kept. ``infer`` is the thin public
wrapper (the model's own settings, with ``iters``/``scale``/``refine`` overrides); ``network_pass`` is one pass on a
pair as given, optionally started from a disparity. ``optstereo.export.infer_onnx`` runs an ONNX graph through the
same ``run``. Writing the results to files: ``optstereo.inference.outputs``.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from torch import nn

from optstereo.checkpoint import model_inference
from optstereo.choices import AMP_MODES, REFINERS, AmpMode
from optstereo.inference.cascade import coarse_start, grid_start, jump_limit, photometric_select
from optstereo.inference.config import InferenceConfig
from optstereo.inference.padding import InputPadder, divisor_of
from optstereo.inference.rescale import (
    adaptive_factor,
    budget_factor,
    disparity_to_size,
    rescaled_pair,
    scaled_size,
    shrink_factor,
)
from pvm_labeler.common.version import cpuinfo_flags

logger = logging.getLogger(__name__)

Image = npt.NDArray[np.uint8]
Disparity = npt.NDArray[np.float32]


def to_batch(image: npt.NDArray[np.uint8], device: torch.device) -> torch.Tensor:
    """(H, W, 3) uint8 RGB -> (1, 3, H, W) float32 in [0, 255] on ``device`` (the network's input)."""
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) RGB image, got shape {image.shape}")
    return torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1))).float()[None].to(device)


def check_image(image: Any, which: str) -> None:
    """ValueError unless ``image`` is an (H, W, 3) uint8 RGB array, naming what it is and how to get there: a grey
    (H, W) or (H, W, 1) image, RGBA, channels first (3, H, W), float or 16-bit values (the network reads 0-255
    intensities: a float image in [0, 1] would be read as nearly black, without an error)."""
    shape = getattr(image, "shape", None)
    dtype = getattr(image, "dtype", None)
    if shape is None or dtype is None:
        raise ValueError(f"{which} image must be a NumPy array (H, W, 3) uint8 RGB, got {type(image).__name__}")
    if len(shape) == 2 or (len(shape) == 3 and shape[2] == 1):
        hint = "a grey image: np.repeat(image.reshape(H, W, 1), 3, axis=2) gives RGB"
    elif len(shape) == 3 and shape[2] == 4:
        hint = "RGBA: image[..., :3]"
    elif len(shape) == 3 and shape[0] in (1, 3) and shape[2] not in (1, 3):
        hint = "channels first: image.transpose(1, 2, 0)"
    elif len(shape) != 3 or shape[2] != 3:
        hint = "not an image of one view"
    else:
        hint = ""
    if hint:
        raise ValueError(f"{which} image must be (H, W, 3) uint8 RGB, got shape {tuple(shape)} ({hint})")
    if 0 in shape[:2]:
        raise ValueError(f"{which} image is empty: shape {tuple(shape)}")
    if dtype != np.uint8:
        floats = np.dtype(dtype).kind == "f"
        how = ("values in [0, 1]? (image * 255).round().astype(np.uint8)" if floats and np.nanmax(image) <= 1.0 else
               "values 0-255? image.round().clip(0, 255).astype(np.uint8)" if floats else
               "16-bit? ((image.astype(np.uint32) + 128) // 257).astype(np.uint8), as read_image rounds"
               if np.dtype(dtype) == np.uint16 else
               "image.astype(np.uint8) if its values are 0-255")
        raise ValueError(f"{which} image must be uint8 (0-255) RGB, got {dtype}: {how}; "
                         "pvm_labeler.common.io.read_image reads any image file as such")


NATIVE_BF16_FLAGS = ("avx512_bf16", "amx_bf16", "bf16")  # x86 /proc/cpuinfo "flags"; aarch64 "Features"


@functools.cache
def cpu_has_native_bf16() -> bool:
    """True when the CPU has bf16 arithmetic in hardware (x86 AVX512-BF16 or AMX, aarch64 BF16).

    Without it torch emulates bf16 convolutions, which runs many times slower than float32. torch's own check
    (``torch.ops.mkldnn._is_mkldnn_bf16_supported``, the fallback where /proc/cpuinfo is missing) is also true on
    AVX-512 CPUs without AVX512-BF16, which emulate.
    """
    flags = cpuinfo_flags()
    if flags is not None:
        return any(flag in flags for flag in NATIVE_BF16_FLAGS)
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


_bf16_warned = False  # once per process: infer() enters inference_autocast for every frame


def warn_if_emulated_bf16(amp: AmpMode, device: torch.device) -> None:
    """Log a warning (once per process) for ``--amp bf16`` on a CPU that would emulate bf16."""
    global _bf16_warned
    if amp == "bf16" and device.type == "cpu" and not _bf16_warned and not cpu_has_native_bf16():
        _bf16_warned = True
        logger.warning("--amp bf16: this CPU has no native bf16 (AVX512-BF16/AMX); bf16 is emulated and much "
                       "slower than float32 here, use --amp none")


def inference_autocast(amp: AmpMode, device: torch.device) -> contextlib.AbstractContextManager:
    """Autocast for inference: bf16 on CPU or CUDA, fp16 on CUDA only; ``none`` = float32.

    The model keeps the correlation volume, the lookup and the disparity accumulator in float32 either way.
    """
    if amp not in AMP_MODES:
        raise ValueError(f"amp must be one of {AMP_MODES}, got {amp!r}")
    if amp == "none":
        return contextlib.nullcontext()
    if amp == "fp16" and device.type != "cuda":
        raise ValueError("amp fp16 needs a CUDA device; use bf16 on CPU")
    warn_if_emulated_bf16(amp, device)
    return torch.autocast(device_type=device.type, dtype=torch.bfloat16 if amp == "bf16" else torch.float16)


def check_refine(refine: str) -> None:
    """Raise ValueError unless ``refine`` names a post-filter (InferenceConfig.refine)."""
    if refine not in REFINERS:
        raise ValueError(f"refine must be one of {REFINERS}, got {refine!r}")


def apply_refine(disp: npt.NDArray[np.float32], left: npt.NDArray[np.uint8], refine: str,
                 device: torch.device | str = "cpu") -> npt.NDArray[np.float32]:
    """The post-filter ``refine`` ("none" or "wmedian", see InferenceConfig.refine) on an (H, W) float32 disparity of
    the (H, W, 3) uint8 left image; on a CUDA ``device`` the median runs there (``optstereo.inference.refine_torch``),
    on the CPU
    in the labeler's numba kernel."""
    check_refine(refine)
    if refine == "none":
        return disp
    if torch.device(device).type == "cuda":
        from optstereo.inference.refine_torch import (
            weighted_median_torch,  # lazy: numba (~0.4 s) loads only when wmedian runs
        )

        return weighted_median_torch(disp, left, device=device)
    from pvm_labeler.refine import weighted_median  # lazy: numba (~0.4 s) loads only when wmedian runs

    return weighted_median(disp, left)


@dataclass(frozen=True)
class Inference:
    """One pair's disparity and the factor its pair was resized by for the network's final pass."""

    disparity: Disparity
    input_scale: float


def model_inference_config(model: nn.Module, iters: int | None = None, scale: float | None = None,
                           refine: str | None = None) -> InferenceConfig:
    """The model's InferenceConfig (``model.inference_config``, else the defaults) with the caller's overrides: a
    given ``scale`` is final (no adaptive pass, no pixel-budget enlargement); ``iters``/``refine`` None keep the
    model's."""
    config = model_inference(model)
    if scale is not None:
        config = config.fixed(scale)
    changes: dict = {}
    if iters is not None:
        changes["iters"] = iters
    if refine is not None:
        check_refine(refine)
        changes["refine"] = refine
    return config.replace(**changes) if changes else config


def infer(
    model: nn.Module,
    left: Image,
    right: Image,
    iters: int | None = None,
    device: torch.device | str = "cpu",
    amp: AmpMode = "none",
    scale: float | None = None,
    refine: str | None = None,
) -> Disparity:
    """Full-resolution disparity of one pair, run as the model's InferenceConfig says (:func:`run`).

    Args:
        model: OptStereo-like model (test_mode=True returns (low, full)).
        left, right: (H, W, 3) uint8 RGB of equal shape (any H, W: padded to the model's multiple and un-padded).
        iters: GRU iterations (None = the config's, else the model's default).
        amp: ``none`` (float32), ``bf16`` (CPU with AVX512-BF16/AMX, or CUDA) or ``fp16`` (CUDA).
        scale: resize both images by this factor before the network and bring the disparity back to the input's
            size and pixels; 1 = as given, None = the model's own (``InferenceConfig.scale``, with its adaptive pass
            for small pairs when set). A given scale is final.
        refine: post-filter at the input's size, guided by ``left``: "none", "wmedian"; None = the model's own.

    Returns:
        (H, W) float32 disparity in pixels of the input (positive, left(x) matches right(x - d)).
    """
    return run(model, left, right, model_inference_config(model, iters, scale, refine), device, amp).disparity


@torch.inference_mode()
def run(model: nn.Module, left: Image, right: Image, config: InferenceConfig | None = None,
        device: torch.device | str = "cpu", amp: AmpMode = "none") -> Inference:
    """The disparity of one (H, W, 3) uint8 pair as ``config`` says (None = the model's ``model.inference_config``).

    In order: the zero-start pass at :func:`first_scale` (``config.scale``, a small pair enlarged toward the pixel
    budget with ``enlarge_max``; unless only a coarse-started one is wanted); with ``adaptive_ref_disp``, a second one
    at the enlarged scale when :func:`optstereo.inference.rescale.adaptive_factor` asks for it; with ``coarse_start``
    the pass started from ``optstereo.inference.cascade.coarse_start`` on the same resized, padded pair, and with
    ``select`` the per-pixel choice between it and the zero-start pass; then the post-filter.
    Returns the (H, W) float32 disparity in the input's pixels and the scale of the final pass.
    """
    config = (config or model_inference(model)).validate()
    check_image(left, "left")
    check_image(right, "right")
    if left.shape != right.shape:
        raise ValueError(f"left/right shapes differ: {left.shape} vs {right.shape}")
    device = torch.device(device)
    scale = first_scale(config, left.shape)
    check_width(model, left.shape, scale)
    if scale != config.scale:
        logger.info("%dx%d pair run at input scale %.3f (the model's %.3f, %s toward a training-size pair's "
                    "pixels)", left.shape[1], left.shape[0], scale, config.scale,
                    "enlarged" if scale > config.scale else "shrunk")
    zero = coarse = None
    with _eval_mode(model):
        if not config.coarse_start or config.select or config.adaptive:
            zero = pass_at_scale(model, left, right, scale, None, config.iters, device, amp)
            final = final_scale(config, zero, left.shape)
            if final != scale:
                logger.info("adaptive input scale: %dx%d pair enlarged %.3f -> %.3f", left.shape[1], left.shape[0],
                            scale, final)
                scale = final
                zero = None if config.coarse_start and not config.select else \
                    pass_at_scale(model, left, right, scale, None, config.iters, device, amp)
        if config.coarse_start:
            coarse = pass_at_scale(model, left, right, scale, None, config.iters, device, amp, coarse=True)
    if coarse is None:
        disp = zero
    elif config.select:
        disp = photometric_select(left, right, (coarse, zero), max_jump=jump_limit(left.shape[1], config.select_jump))
    else:
        disp = coarse
    return Inference(apply_refine(disp, left, config.refine, device), scale)


def first_scale(config: InferenceConfig, shape: tuple[int, ...]) -> float:
    """The input scale of :func:`run`'s first pass on an (H, W, ...) pair: ``config.scale``; when
    ``config.enlarge_max`` > 1, the larger of it and the pixel budget's enlargement of the pair as given
    (``budget_factor``), so a pair is never run smaller than the budget asks (registration T8); with
    ``config.shrink_large``, at most ``scale`` x ``shrink_factor``, so that a pair of over 1.21x a training-size
    pair's pixels runs with as many pixels as one does at ``scale`` (T12)."""
    if config.shrink_large and (shrink := shrink_factor(shape, config.adaptive_ref_pixels)) < 1.0:
        return config.scale * shrink
    if config.enlarge_max > 1:
        return max(config.scale, budget_factor(shape, config.adaptive_ref_pixels, config.enlarge_max))
    return config.scale


def final_scale(config: InferenceConfig, zero: Disparity | None, shape: tuple[int, ...]) -> float:
    """The input scale of :func:`run`'s final pass on an (H, W, ...) pair: :func:`first_scale`, times the adaptive
    enlargement (``adaptive_factor``, counted from the first pass) of ``zero`` (the zero-start pass at the first
    scale, at the input's size; needed only with ``config.adaptive``) when it is one."""
    first = first_scale(config, shape)
    if not config.adaptive:
        return first
    if zero is None:
        raise ValueError("the adaptive scale needs the zero-start pass's disparity")
    return first * adaptive_factor(zero, config.adaptive_ref_disp, config.adaptive_ref_pixels,
                                   prior=first / config.scale)


def check_width(model: nn.Module, shape: tuple[int, ...], scale: float) -> None:
    """ValueError, in the pair's own pixels, when an (H, W, ...) pair at input ``scale`` is narrower (padded) than
    the model's cost-volume pyramid takes (``model.min_width``; the model's own error named the padded width)."""
    need = getattr(model, "min_width", None)
    if need is None:
        return
    width = scaled_size(shape, scale)[1] if scale != 1.0 else shape[1]
    divisor = divisor_of(model)
    padded = -(-width // divisor) * divisor
    if padded < need:
        raise ValueError(f"the pair is {shape[1]}x{shape[0]} px: at input scale {scale:.3g} the network sees it "
                         f"{padded} px wide (padded), and its cost-volume pyramid needs >= {need}: give a pair at "
                         f"least {math.ceil(need / scale)} px wide, or a larger scale")


@torch.inference_mode()
def pass_at_scale(model: nn.Module, left: Image, right: Image, scale: float = 1.0, start: Disparity | None = None,
                  iters: int | None = None, device: torch.device | str = "cpu", amp: AmpMode = "none",
                  coarse: bool = False) -> Disparity:
    """One network pass on the pair resized by ``scale``, back at the input's (H, W) and pixels; no post-filter.

    Its GRU starts from ``start`` (an (H, W) float32 disparity of the input, resized with the pair), with ``coarse``
    from ``optstereo.inference.cascade.coarse_start`` of the same resized, padded pair (the training's own start), or
    from
    zero. The building block of :func:`run`'s passes, of a sequence's started frames and of a confidence's mirrored
    pass.
    """
    device = torch.device(device)
    if scale == 1.0:
        return _padded_pass(model, left, right, start, iters, device, amp, coarse)
    left_s, right_s = rescaled_pair(left, right, scale)
    start_s = None if start is None else disparity_to_size(start, left_s.shape[:2])
    disp = _padded_pass(model, left_s, right_s, start_s, iters, device, amp, coarse)
    return disparity_to_size(disp, left.shape[:2])


def network_pass(model: nn.Module, left: Image, right: Image, start: Disparity | None = None,
                 iters: int | None = None, device: torch.device | str = "cpu", amp: AmpMode = "none") -> Disparity:
    """One network pass on a pair as given: (H, W, 3) uint8 each -> (H, W) float32 disparity, no resizing, no filter;
    the GRU starts from ``start`` ((H, W) float32 disparity of the pair) or from zero (:func:`pass_at_scale` at 1)."""
    return pass_at_scale(model, left, right, 1.0, start, iters, device, amp)


def _padded_pass(model: nn.Module, left: Image, right: Image, start: Disparity | None, iters: int | None,
                 device: torch.device, amp: AmpMode, coarse: bool) -> Disparity:
    """The pair padded to the model's multiple, one forward in eval mode, un-padded: (H, W) float32. ``start`` is
    padded like the pair and averaged onto the 1/8 grid (``optstereo.inference.cascade.grid_start``)."""
    left_t, right_t = to_batch(left, device), to_batch(right, device)
    padder = InputPadder(left_t.shape, divis_by=divisor_of(model))
    left_t, right_t = padder.pad(left_t, right_t)
    extra = {}
    if start is not None:
        start_t = torch.from_numpy(np.ascontiguousarray(start, np.float32))[None, None].to(device)
        extra["disp_init"] = grid_start(padder.pad(start_t)[0])
    with _eval_mode(model), inference_autocast(amp, device):
        if coarse:
            extra["disp_init"] = coarse_start(model, left_t, right_t, iters)
        _, full = model(left_t, right_t, iters=iters, test_mode=True, **extra)
    return padder.unpad(full)[0, 0].float().cpu().numpy().astype(np.float32)


@contextlib.contextmanager
def _eval_mode(model: nn.Module) -> Iterator[None]:
    """``model`` in eval mode inside the block, its own mode restored after."""
    was_training = model.training
    model.eval()
    try:
        yield
    finally:
        model.train(was_training)
