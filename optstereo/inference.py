"""Inference and disparity files in the field's formats: ``optstereo-predict``.

Outputs per frame (``formats`` picks them): ``png`` KITTI 16-bit PNG (disparity x 256, 0 = invalid), ``pfm``
(float32, Middlebury/Scene Flow), ``npy`` (float32), ``color`` (8-bit colour rendering for people). The KITTI form
(``kitti_layout=True``) names files as the benchmark's submission expects: ``disp_0/<frame>_10.png``.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from torch import nn

from optstereo.padding import InputPadder, divisor_of
from optstereo.rescale import PairRun, scaled_passes
from optstereo.submission import write_submission
from pvm_labeler.common.version import cpuinfo_flags

logger = logging.getLogger(__name__)

FORMATS = ("png", "pfm", "npy", "color")
GEOMETRY_FORMATS = ("depth-png", "depth-pfm", "depth-npy", "ply")  # need a calibration (optstereo.geometry)
DEFAULT_FORMATS = ("png", "color")


def to_batch(image: npt.NDArray[np.uint8], device: torch.device) -> torch.Tensor:
    """(H, W, 3) uint8 RGB -> (1, 3, H, W) float32 in [0, 255] on ``device`` (the network's input)."""
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) RGB image, got shape {image.shape}")
    return torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1))).float()[None].to(device)


INFER_AMP = ("none", "bf16", "fp16")


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


def warn_if_emulated_bf16(amp: str, device: torch.device) -> None:
    """Log a warning (once per process) for ``--amp bf16`` on a CPU that would emulate bf16."""
    global _bf16_warned
    if amp == "bf16" and device.type == "cpu" and not _bf16_warned and not cpu_has_native_bf16():
        _bf16_warned = True
        logger.warning("--amp bf16: this CPU has no native bf16 (AVX512-BF16/AMX); bf16 is emulated and much "
                       "slower than float32 here, use --amp none")


def inference_autocast(amp: str, device: torch.device) -> contextlib.AbstractContextManager:
    """Autocast for inference: bf16 on CPU or CUDA, fp16 on CUDA only; ``none`` = float32.

    The model keeps the correlation volume, the lookup and the disparity accumulator in float32 either way.
    """
    if amp not in INFER_AMP:
        raise ValueError(f"amp must be one of {INFER_AMP}, got {amp!r}")
    if amp == "none":
        return contextlib.nullcontext()
    if amp == "fp16" and device.type != "cuda":
        raise ValueError("amp fp16 needs a CUDA device; use bf16 on CPU")
    warn_if_emulated_bf16(amp, device)
    return torch.autocast(device_type=device.type, dtype=torch.bfloat16 if amp == "bf16" else torch.float16)


def model_input_scale(model: nn.Module) -> float:
    """The input scale a model's config records (``ModelConfig.input_scale``), 1.0 for a model without one."""
    return float(getattr(getattr(model, "config", None), "input_scale", 1.0))


def model_refine(model: nn.Module) -> str:
    """The post-filter a model's config records (``ModelConfig.refine``), "none" for a model without one."""
    return str(getattr(getattr(model, "config", None), "refine", "none"))


def check_refine(refine: str) -> None:
    """Raise ValueError unless ``refine`` names a post-filter (ModelConfig.refine)."""
    from optstereo.models.config import REFINERS

    if refine not in REFINERS:
        raise ValueError(f"refine must be one of {REFINERS}, got {refine!r}")


def apply_refine(disp: npt.NDArray[np.float32], left: npt.NDArray[np.uint8], refine: str,
                 device: torch.device | str = "cpu") -> npt.NDArray[np.float32]:
    """The post-filter ``refine`` ("none" or "wmedian", see ModelConfig.refine) on an (H, W) float32 disparity of the
    (H, W, 3) uint8 left image; on a CUDA ``device`` the median runs there (``optstereo.refine_torch``), on the CPU
    in the labeler's numba kernel."""
    check_refine(refine)
    if refine == "none":
        return disp
    if torch.device(device).type == "cuda":
        from optstereo.refine_torch import weighted_median_torch

        return weighted_median_torch(disp, left, device=device)
    from pvm_labeler.refine import weighted_median

    return weighted_median(disp, left)


def model_scale_refs(model: nn.Module) -> tuple[float, int] | None:
    """(scale_ref_disp, scale_ref_pixels) of a model whose config records an adaptive input scale, else None."""
    config = getattr(model, "config", None)
    ref_disp = float(getattr(config, "scale_ref_disp", 0.0))
    return (ref_disp, int(getattr(config, "scale_ref_pixels", 0))) if ref_disp > 0 else None


@dataclass(frozen=True)
class Inference:
    """One pair's disparity and the factor its pair was resized by for the network's final pass."""

    disparity: npt.NDArray[np.float32]
    input_scale: float


def infer(
    model: nn.Module,
    left: npt.NDArray[np.uint8],
    right: npt.NDArray[np.uint8],
    iters: int | None = None,
    device: torch.device | str = "cpu",
    amp: str = "none",
    scale: float | None = None,
    refine: str | None = None,
) -> npt.NDArray[np.float32]:
    """Full-resolution disparity of one pair.

    Args:
        model: OptStereo-like model (test_mode=True returns (low, full)).
        left, right: (H, W, 3) uint8 RGB of equal shape (any H, W: padded to the model's multiple and un-padded).
        iters: GRU iterations (None = the model's default).
        amp: ``none`` (float32), ``bf16`` (CPU with AVX512-BF16/AMX, or CUDA) or ``fp16`` (CUDA).
        scale: resize both images by this factor before the network (see :func:`rescaled_pair`) and bring the
            disparity back to the input's size and pixel units; 1 = as given, None = the model's own
            (:func:`model_input_scale`, enlarged further for a small pair when the model records an adaptive
            scale: :func:`infer_scaled`).
        refine: post-filter of the disparity at the input's size, guided by ``left``: "none", "wmedian"; None =
            the model's own (:func:`model_refine`).

    Returns:
        (H, W) float32 disparity in pixels of the input (positive, left(x) matches right(x - d)).
    """
    return infer_scaled(model, left, right, iters, device, amp, scale, refine).disparity


@torch.inference_mode()
def infer_scaled(
    model: nn.Module,
    left: npt.NDArray[np.uint8],
    right: npt.NDArray[np.uint8],
    iters: int | None = None,
    device: torch.device | str = "cpu",
    amp: str = "none",
    scale: float | None = None,
    refine: str | None = None,
) -> Inference:
    """:func:`infer`, also returning the input scale of the final pass.

    With ``scale`` None and a model that records ``scale_ref_disp`` (:func:`model_scale_refs`), the first pass at
    the model's input scale decides whether a second, larger one runs (:func:`optstereo.rescale.adaptive_factor`):
    a small pair with small disparities is enlarged until they match the model's training pairs. A given ``scale``
    is always used as it is. A model with ``ModelConfig.cascade`` starts the final pass's GRU from a pass at half its
    scale (optstereo.cascade) instead of zero; with ``ModelConfig.cascade_select``, per pixel the better matching of
    that pass and the zero-start one (within ``ModelConfig.cascade_select_jump`` of it, when set).
    """
    if left.shape != right.shape:
        raise ValueError(f"left/right shapes differ: {left.shape} vs {right.shape}")
    refs = model_scale_refs(model) if scale is None else None
    scale = model_input_scale(model) if scale is None else scale
    refine = model_refine(model) if refine is None else refine
    check_refine(refine)  # before the network runs, not after
    device = torch.device(device)
    config = getattr(model, "config", None)
    cascade = bool(getattr(config, "cascade", False))
    select = bool(getattr(config, "cascade_select", False))
    jump = float(getattr(config, "cascade_select_jump", 0.0))
    disp, final = scaled_passes(network_run(model, iters, device, amp), left, right, scale, refs, cascade, select,
                                jump)
    if final != scale:
        logger.info("adaptive input scale: %dx%d pair enlarged %.3f -> %.3f", left.shape[1], left.shape[0], scale,
                    final)
    return Inference(apply_refine(disp, left, refine, device), final)


def network_run(model: nn.Module, iters: int | None = None, device: torch.device | str = "cpu",
                amp: str = "none") -> PairRun:
    """The network as an ``optstereo.rescale.PairRun``: (left, right, start or None) -> (H, W) float32 disparity of
    the pair as given, without gradients; the building block of ``infer``'s passes (``scaled_passes``)."""
    device = torch.device(device)

    def run(left: npt.NDArray[np.uint8], right: npt.NDArray[np.uint8],
            start: npt.NDArray[np.float32] | None) -> npt.NDArray[np.float32]:
        with torch.inference_mode():
            return _network(model, left, right, iters, device, amp, start)

    return run


def _network(model: nn.Module, left: npt.NDArray[np.uint8], right: npt.NDArray[np.uint8], iters: int | None,
             device: torch.device, amp: str, start: npt.NDArray[np.float32] | None = None) -> npt.NDArray[np.float32]:
    """The network's (H, W) float32 disparity of a pair as given (padded to its multiple and un-padded), its GRU
    started from ``start`` ((H, W) disparity of the pair, padded like it and averaged onto the 1/8 grid) or zero."""
    was_training = model.training
    model.eval()
    try:
        left_t, right_t = to_batch(left, device), to_batch(right, device)
        padder = InputPadder(left_t.shape, divis_by=divisor_of(model))
        left_t, right_t = padder.pad(left_t, right_t)
        extra = {}
        if start is not None:
            from optstereo.cascade import grid_start

            start_t = torch.from_numpy(np.ascontiguousarray(start, np.float32))[None, None].to(device)
            extra["disp_init"] = grid_start(padder.pad(start_t)[0])
        with inference_autocast(amp, device):
            _, full = model(left_t, right_t, iters=iters, test_mode=True, **extra)
        disp = padder.unpad(full)[0, 0]
    finally:
        model.train(was_training)
    return disp.float().cpu().numpy().astype(np.float32)


def colorize(disp: npt.NDArray[np.float32], max_disp: float | None = None) -> npt.NDArray[np.uint8]:
    """(H, W, 3) uint8 colour rendering of a disparity map (NaN = black), via the labeler's viz module."""
    try:
        from pvm_labeler.common.viz import colorize_disparity
    except ImportError:  # viz is optional for inference; fall back to OpenCV's turbo map
        import cv2

        finite = np.isfinite(disp)
        vmax = max_disp or (float(disp[finite].max()) if finite.any() else 1.0)
        grey = np.clip(np.nan_to_num(disp) / max(vmax, 1e-6) * 255.0, 0, 255).astype(np.uint8)
        out = cv2.applyColorMap(grey, cv2.COLORMAP_TURBO)[..., ::-1].copy()
        out[~finite] = 0
        return out
    return colorize_disparity(disp, max_disp=max_disp)


def write_disparity(
    out_dir: Path, name: str, disp: npt.NDArray[np.float32], formats: Iterable[str] = DEFAULT_FORMATS,
    *, kitti_layout: bool = False, max_disp: float | None = None,
) -> dict[str, Path]:
    """Write one disparity map in the requested formats; returns format -> path.

    With ``kitti_layout`` the 16-bit PNG goes to ``out_dir/disp_0/<name>.png`` (the KITTI submission layout;
    ``name`` is then the frame's file stem such as ``000000_10``) and the others into sibling folders.
    """
    from pvm_labeler.common.io import write_image, write_kitti_disp, write_npy, write_pfm

    formats = tuple(f for f in formats if f not in GEOMETRY_FORMATS)
    unknown = sorted(set(formats) - set(FORMATS))
    if unknown:
        raise ValueError(f"unknown output formats {unknown}; choose from {FORMATS}")
    out_dir = Path(out_dir)
    folders = {"png": "disp_0", "pfm": "pfm", "npy": "npy", "color": "color"} if kitti_layout else {}
    paths: dict[str, Path] = {}
    for fmt in formats:
        folder = out_dir / folders.get(fmt, "")
        folder.mkdir(parents=True, exist_ok=True)
        if fmt == "png":
            paths[fmt] = folder / f"{name}.png"
            write_kitti_disp(paths[fmt], disp)
        elif fmt == "pfm":
            paths[fmt] = folder / f"{name}.pfm"
            write_pfm(paths[fmt], disp.astype(np.float32))
        elif fmt == "npy":
            paths[fmt] = folder / f"{name}.npy"
            write_npy(paths[fmt], disp.astype(np.float32))
        else:
            paths[fmt] = folder / f"{name}_color.png"
            write_image(paths[fmt], colorize(disp, max_disp))
    return paths


def write_geometry(
    out_dir: Path, name: str, disp: npt.NDArray[np.float32], image: npt.NDArray[np.uint8], calib: Any,
    formats: Iterable[str], max_depth: float = float("inf"),
) -> dict[str, Path]:
    """Depth (16-bit mm PNG, PFM/NPY in m) and a coloured PLY point cloud of one prediction; format -> path."""
    from optstereo.geometry import depth_to_points, disparity_to_depth, write_depth_png, write_ply
    from pvm_labeler.common.io import write_npy, write_pfm

    wanted = [f for f in formats if f in GEOMETRY_FORMATS]
    if not wanted:
        return {}
    if calib is None:
        raise ValueError(f"formats {wanted} need a calibration: pass --calib FILE")
    depth = disparity_to_depth(disp, calib, max_depth)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    for fmt in wanted:
        if fmt == "depth-png":
            paths[fmt] = out_dir / f"{name}_depth.png"
            write_depth_png(paths[fmt], depth)
        elif fmt == "depth-pfm":
            paths[fmt] = out_dir / f"{name}_depth.pfm"
            write_pfm(paths[fmt], depth)
        elif fmt == "depth-npy":
            paths[fmt] = out_dir / f"{name}_depth.npy"
            write_npy(paths[fmt], depth)
        else:
            paths[fmt] = out_dir / f"{name}.ply"
            write_ply(paths[fmt], *depth_to_points(depth, calib, image))
    return paths


def predict_pair(
    model: nn.Module, left_path: Path, right_path: Path, out_dir: Path, *, iters: int | None = None,
    formats: Iterable[str] = DEFAULT_FORMATS, device: torch.device | str = "cpu", amp: str = "none",
    calib: Any = None, max_depth: float = float("inf"), scale: float | None = None, refine: str | None = None,
) -> dict[str, Path]:
    """Predict one pair from image files and write ``<left stem>.<ext>`` files into out_dir (depth/PLY: ``calib``)."""
    from pvm_labeler.common.io import read_image

    left, right = read_image(left_path), read_image(right_path)
    if left.shape != right.shape:
        raise ValueError(f"left/right sizes differ: {left.shape[:2]} vs {right.shape[:2]}: {left_path}, {right_path}")
    t0 = time.perf_counter()
    disp = infer(model, left, right, iters=iters, device=device, amp=amp, scale=scale, refine=refine)
    logger.info("%s: %.2f s", left_path, time.perf_counter() - t0)
    stem = Path(left_path).stem
    return {**write_disparity(out_dir, stem, disp, formats),
            **write_geometry(out_dir, stem, disp, left, calib, formats, max_depth)}


def predict_dataset(
    model: nn.Module, dataset: str, root: Path | None, out_dir: Path, *, split: str = "training",
    iters: int | None = None, formats: Iterable[str] = DEFAULT_FORMATS, device: torch.device | str = "cpu",
    limit: int | None = None, amp: str = "none", submission: Path | None = None,
    reader_options: dict[str, Any] | None = None, scale: float | None = None, refine: str | None = None,
) -> list[dict[str, Path]]:
    """Predict every pair of a dataset; KITTI datasets get the submission layout ``disp_0/<frame>_10.png``.

    With ``submission`` the ``_10`` frames are also zipped (and checked) for the KITTI benchmark server.
    """
    from pvm_labeler.common.datasets import discover, load_pair

    refs = discover(dataset, root, split=split, **(reader_options or {}))[:limit]
    if submission is not None and not dataset.startswith("kitti"):
        raise ValueError(f"--submission writes the KITTI benchmark layout; dataset {dataset!r} is not KITTI")
    written = []
    for ref in refs:
        sample = load_pair(ref)
        disp = infer(model, sample.left, sample.right, iters=iters, device=device, amp=amp, scale=scale,
                     refine=refine)
        written.append(write_disparity(out_dir, ref.frame_id, disp, formats, kitti_layout=dataset.startswith("kitti")))
    if submission is not None:
        write_submission(out_dir, submission, refs)
    return written
