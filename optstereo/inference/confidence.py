"""Per-pixel confidence in [0, 1] of a disparity map, and the sparsification curve that scores one.

Three measures, all without ground truth (``results/confidence.json`` scores them on the KITTI 2015 GT frames):

- ``photometric``: 1 - the photometric error of the right view warped by the disparity onto the left, averaged
  over a 7x7 box (``optstereo.inference.cascade.photometric_costs``: 0.85 (1 - SSIM) / 2 + 0.15 L1, the reconstruction
  loss's own per-pixel form). No extra network pass.
- ``lr``: left-right consistency. One more network pass on the mirrored pair (both images flipped, swapped) gives
  the right view's disparity; confidence exp(-|d_L(x) - d_R(x - d_L(x))| / LR_SCALE), 0 where x - d leaves the
  image.
- ``spread``: exp(-std / SPREAD_SCALE) of the GRU's last SPREAD_LAST full-resolution predictions of one more pass
  (the forward's list output).

:data:`DEFAULT_METHOD` is the one the measurement chose. Its scale constants only map an error onto [0, 1]; the
sparsification curve depends only on the order of the pixels, so the choice of the constants does not change it.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np
import numpy.typing as npt
import torch
from torch import nn

from optstereo.inference.cascade import photometric_costs
from optstereo.inference.engine import model_inference_config, pass_at_scale, run, to_batch
from optstereo.inference.padding import InputPadder, divisor_of
from optstereo.training.augment import right_view
from pvm_labeler.common.datasets import safe_stem
from pvm_labeler.common.io import write_image, write_npy

Image = npt.NDArray[np.uint8]
Map = npt.NDArray[np.float32]

METHODS = ("photometric", "lr", "spread", "photometric+lr")
#: Chosen on KITTI 2015 (results/confidence.json): the lowest sparsification AUC per extra network pass.
DEFAULT_METHOD = "photometric+lr"
LR_SCALE = 1.0  # px: an LR mismatch of 1 px gives confidence 1/e
SPREAD_SCALE = 0.25  # px
SPREAD_LAST = 4
#: Densities (fractions of the pixels kept) the sparsification curve is sampled at: 5 %, 10 %, ..., 100 %.
DENSITIES = tuple(round(0.05 * k, 2) for k in range(1, 21))


def photometric_confidence(left: Image, right: Image, disp: Map) -> Map:
    """(H, W) float32 in [0, 1]: 1 - the 7x7-box photometric error of ``right`` warped by ``disp`` onto ``left``
    ((H, W, 3) uint8 each; 0 where the warp leaves the image)."""
    cost = photometric_costs(left, right, [np.nan_to_num(disp, nan=0.0).astype(np.float32)])[0]
    return np.clip(1.0 - cost, 0.0, 1.0).astype(np.float32) * np.isfinite(disp)


def right_view_disparity(model: nn.Module, left: Image, right: Image, device: torch.device | str = "cpu",
                         amp: str = "none", iters: int | None = None, scale: float = 1.0) -> Map:
    """(H, W) float32 disparity of the RIGHT view (right(x) matches left(x + d)), from one network pass on the
    mirrored pair: flip both images left-right and swap them, so the right view becomes a left view."""
    return right_view(lambda l, r: pass_at_scale(model, l, r, scale, None, iters, device, amp), left, right)


def lr_difference(disp_left: Map, disp_right: Map) -> Map:
    """(H, W) float32 |d_L(x) - d_R(x - d_L(x))| (d_R linearly interpolated along the row), inf where x - d_L(x)
    falls outside the image or either value is not finite."""
    h, w = disp_left.shape
    xs = np.arange(w, dtype=np.float32)[None] - disp_left
    x0 = np.floor(xs)
    frac = xs - x0
    inside = np.isfinite(xs) & (x0 >= 0) & (x0 + 1 <= w - 1)
    i0 = np.clip(np.nan_to_num(x0, nan=0), 0, w - 1).astype(np.int64)
    i1 = np.clip(i0 + 1, 0, w - 1)
    rows = np.arange(h)[:, None]
    at = (1 - frac) * disp_right[rows, i0] + frac * disp_right[rows, i1]
    diff = np.abs(disp_left - at)
    return np.where(inside & np.isfinite(diff), diff, np.inf).astype(np.float32)


def lr_confidence(model: nn.Module, left: Image, right: Image, disp: Map, device: torch.device | str = "cpu",
                  amp: str = "none", scale: float = 1.0, iters: int | None = None) -> Map:
    """(H, W) float32 in [0, 1]: exp(-LR difference / LR_SCALE) of ``disp`` against one mirrored pass at ``scale``
    and ``iters`` GRU iterations (None: the network's default)."""
    diff = lr_difference(disp, right_view_disparity(model, left, right, device, amp, iters=iters, scale=scale))
    return np.exp(-diff / LR_SCALE).astype(np.float32)


@torch.inference_mode()
def iteration_predictions(model: nn.Module, left: Image, right: Image, device: torch.device | str = "cpu",
                          iters: int | None = None) -> npt.NDArray[np.float32]:
    """(K, H, W) float32: the full-resolution prediction after each of the K GRU iterations of one zero-start pass
    (the forward's list output, which training uses), float32, no autocast."""
    device = torch.device(device)
    was_training = model.training
    model.eval()
    try:
        left_t, right_t = to_batch(left, device), to_batch(right, device)
        padder = InputPadder(left_t.shape, divis_by=divisor_of(model))
        preds = model(*padder.pad(left_t, right_t), iters=iters, test_mode=False)
        return torch.stack([padder.unpad(p)[0, 0] for p in preds]).float().cpu().numpy()
    finally:
        model.train(was_training)


def spread_confidence(model: nn.Module, left: Image, right: Image, device: torch.device | str = "cpu",
                      iters: int | None = None) -> Map:
    """(H, W) float32 in [0, 1]: exp(-std / SPREAD_SCALE) of the last SPREAD_LAST iterations' predictions."""
    preds = iteration_predictions(model, left, right, device, iters)
    return np.exp(-preds[-SPREAD_LAST:].std(axis=0) / SPREAD_SCALE).astype(np.float32)


def confidence_of(model: nn.Module, left: Image, right: Image, disp: Map, method: str = DEFAULT_METHOD,
                  device: torch.device | str = "cpu", amp: str = "none", scale: float = 1.0,
                  iters: int | None = None) -> Map:
    """(H, W) float32 confidence in [0, 1] of ``disp``, the disparity of the (H, W, 3) uint8 pair, by ``method``
    (one of :data:`METHODS`; ``scale`` and ``iters`` are the input scale and GRU iterations of the extra pass of
    ``lr``: those of the pass that made ``disp``)."""
    if method not in METHODS:
        raise ValueError(f"confidence method must be one of {METHODS}, got {method!r}")
    if method == "photometric":
        return photometric_confidence(left, right, disp)
    if method == "lr":
        return lr_confidence(model, left, right, disp, device, amp, scale, iters)
    if method == "spread":
        return spread_confidence(model, left, right, device)
    return photometric_confidence(left, right, disp) * lr_confidence(model, left, right, disp, device, amp, scale,
                                                                     iters)


def infer_with_confidence(model: nn.Module, left: Image, right: Image, *, method: str = DEFAULT_METHOD,
                          iters: int | None = None, device: torch.device | str = "cpu", amp: str = "none",
                          scale: float | None = None, refine: str | None = None) -> tuple[Map, Map]:
    """(disparity, confidence), each (H, W) float32, of one (H, W, 3) uint8 pair: the disparity is exactly
    ``optstereo.inference.engine.infer``'s (same arguments), the confidence :func:`confidence_of` it."""
    config = model_inference_config(model, iters, scale, refine)
    result = run(model, left, right, config, device, amp)
    conf = confidence_of(model, left, right, result.disparity, method, device, amp, result.input_scale, config.iters)
    return result.disparity, conf


def sparsification(confidence: npt.NDArray[np.floating], error: npt.NDArray[np.floating],
                   densities: Iterable[float] = DENSITIES, threshold: float = 3.0) -> npt.NDArray[np.float64]:
    """bad-``threshold`` (% of kept pixels with error > threshold) when only the most confident ``density`` x N of
    the N pixels are kept, per density. ``confidence``, ``error``: (N,) over the GT-valid pixels; equal confidences
    keep their given order (stable sort). The oracle curve is ``sparsification(-error, error)``."""
    confidence, error = np.asarray(confidence).ravel(), np.asarray(error).ravel()
    if confidence.shape != error.shape or not error.size:
        raise ValueError(f"sparsification needs equal non-empty shapes, got {confidence.shape} and {error.shape}")
    bad = (error > threshold)[np.argsort(-confidence, kind="stable")]
    cum = np.cumsum(bad)
    out = []
    for density in densities:
        keep = max(1, int(round(density * error.size)))
        out.append(100.0 * cum[keep - 1] / keep)
    return np.asarray(out, np.float64)


def curve_area(curve: npt.NDArray[np.float64], densities: Iterable[float] = DENSITIES) -> float:
    """Area under a sparsification curve over density (trapezoids; % x fraction, lower is better)."""
    x = np.asarray(tuple(densities), np.float64)
    return float(np.sum((curve[1:] + curve[:-1]) / 2 * np.diff(x)))


#: The file of each confidence format, by frame name.
CONF_NAMES = {"conf-png": "{name}_conf.png", "conf-npy": "{name}_conf.npy"}


def confidence_paths(out_dir: Path, name: str, formats: Iterable[str]) -> dict[str, Path]:
    """format -> the file :func:`write_confidence` writes for frame ``name`` (other formats left out)."""
    name = safe_stem(name)
    return {fmt: Path(out_dir) / CONF_NAMES[fmt].format(name=name) for fmt in formats if fmt in CONF_NAMES}


def write_confidence(out_dir: Path, name: str, conf: Map, formats: Iterable[str]) -> dict[str, Path]:
    """Write ``conf`` as ``conf-png`` (``<name>_conf.png``, uint16 = round(conf x 65535)) and/or ``conf-npy``
    (``<name>_conf.npy``, float32), each atomically; format -> path. ``name`` as
    ``optstereo.inference.outputs.write_disparity``'s."""
    formats = tuple(formats)
    if unknown := [f for f in formats if f not in CONF_NAMES]:
        raise ValueError(f"unknown confidence format {unknown[0]!r}; choose from {', '.join(CONF_NAMES)}")
    paths = confidence_paths(out_dir, name, formats)
    for fmt, path in paths.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        if fmt == "conf-png":
            write_image(path, np.round(np.clip(np.nan_to_num(conf), 0, 1) * 65535).astype(np.uint16))
        else:
            write_npy(path, conf.astype(np.float32))
    return paths
