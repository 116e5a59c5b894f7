"""Stereo video: each frame's GRU starts from the previous frame's answer, with fewer iterations.

The first frame runs the plain path (``optstereo.inference.engine.run``: the model's own passes, scale and
post-filter), so a one-frame sequence equals it exactly. Every later frame runs one network pass at the first
frame's final input scale, its D_s^0 the previous frame's disparity averaged onto the 1/8 grid
(``optstereo.inference.cascade.grid_start``, inside ``optstereo.inference.engine.network_pass``) and ``sequence_iters``
GRU iterations,
then the same post-filter. Between consecutive frames of a video most disparities move by a fraction of a 1/8-grid
cell, so a few iterations finish the walk that a zero start needs all of its iterations for.

A frame starts a new sequence (the plain path again) when its size differs from the frame before, or at a scene cut:
:func:`photometric_change` against the frame before above :data:`SCENE_CUT`. :func:`natural_key` orders frame names
as a video's (``frame_2`` before ``frame_10``).

:func:`temporal_change` is the stability measure of ``results/sequence.json``: the mean |d_t - d_{t-1}| on pixels
whose previous value can be followed into the current frame (dense optical flow between the two left images,
forward-backward consistent and photometrically consistent).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
import torch
from torch import nn

from optstereo.inference.engine import apply_refine, model_inference_config, pass_at_scale, run

logger = logging.getLogger(__name__)

Image = npt.NDArray[np.uint8]
Disparity = npt.NDArray[np.float32]

#: GRU iterations of every frame after the first (`pretrained-accurate`'s own is 8): the start is already within a
#: fraction of a grid cell for most pixels. results/sequence/ measures 4 and 8 against independent frames.
DEFAULT_SEQUENCE_ITERS = 4
#: Pixels whose flow-warped previous left image differs from the current one by more than this (mean |RGB| / 255)
#: are left out of :func:`temporal_change`: occlusions, moving objects, flow failures.
PHOTO_TOLERANCE = 0.04
#: ... and those whose forward and backward flows disagree by more than this many pixels.
FLOW_TOLERANCE = 1.0
#: Width (px) of the grey thumbnails :func:`photometric_change` compares: at 16 px a cell spans ~80 px of a KITTI
#: frame, so the motion between video frames mostly averages out while a new scene's layout and brightness do not.
CUT_WIDTH = 16
#: :func:`photometric_change` above which a frame is a scene cut (a new sequence). Measured on the KITTI frames of
#: ../shared/data (2026-11-27): consecutive frames of a 10 fps video 0.02-0.05 (KITTI 2015 ``_10``/``_11``), every
#: 4th frame of a raw drive and of odometry clips (0.4 s apart, as results/sequence.json runs its drive) 0.04-0.15,
#: consecutive KITTI 2015 scenes (unrelated) 0.03-0.41 (median 0.16). 0.16 sits above every video pair measured, so a
#: drive keeps its sequence; the unrelated scenes it misses are those that look alike at 16 px (road below, sky
#: above), and the datasets of unrelated scenes are refused by optstereo-predict --sequence altogether. A false cut
#: costs one plain pass; a missed one starts the GRU from another scene's disparity.
SCENE_CUT = 0.16


@dataclass
class SequenceState:
    """What a sequence carries from one frame to the next: the last disparity (input size and pixels), the input
    scale of the network's pass (the first frame's final one) and the last left image's thumbnail (scene cuts)."""

    disparity: Disparity | None = None
    scale: float | None = None
    thumbnail: npt.NDArray[np.float32] | None = None


def natural_key(name: str) -> tuple:
    """Sort key of a frame name with its digit runs compared as numbers: ``frame_2`` before ``frame_10``; names equal
    as numbers (``07`` / ``7``) keep a fixed order."""
    parts = re.split(r"(\d+)", name)
    return tuple(int(p) if i % 2 else p for i, p in enumerate(parts)), name


def thumbnail(image: Image) -> npt.NDArray[np.float32]:
    """(h, CUT_WIDTH) float32 grey in [0, 1] of an (H, W, 3) uint8 image, by area averaging (h keeps the aspect)."""
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    height = max(1, round(image.shape[0] * CUT_WIDTH / image.shape[1]))
    return cv2.resize(grey, (CUT_WIDTH, height), interpolation=cv2.INTER_AREA)


def photometric_change(previous: npt.NDArray[np.float32], current: npt.NDArray[np.float32]) -> float:
    """Mean absolute difference of two :func:`thumbnail` s (0 = the same picture, 1 = black vs white); inf when
    their shapes differ."""
    if previous.shape != current.shape:
        return float("inf")
    return float(np.abs(previous - current).mean())


def infer_next(model: nn.Module, left: Image, right: Image, state: SequenceState, *, iters: int | None = None,
               sequence_iters: int = DEFAULT_SEQUENCE_ITERS, device: torch.device | str = "cpu", amp: str = "none",
               scale: float | None = None, refine: str | None = None) -> Disparity:
    """(H, W) float32 disparity of one frame of a sequence; updates ``state`` in place.

    Args:
        model: OptStereo-like model (``disp_init`` accepted by its forward).
        left, right: (H, W, 3) uint8 RGB of the frame.
        state: the sequence so far (a fresh :class:`SequenceState` for the first frame, which runs the plain path, as
            a frame of another size or a scene cut does: :data:`SCENE_CUT`).
        iters: GRU iterations of the first frame (None = the model's own).
        sequence_iters: GRU iterations of every later frame, started from the previous answer.
        scale, refine: as ``optstereo.inference.engine.infer``; later frames reuse the first frame's final scale.
    """
    if sequence_iters < 1:
        raise ValueError(f"sequence_iters must be >= 1, got {sequence_iters}")
    prev, thumb = state.disparity, thumbnail(left)
    change = 0.0 if state.thumbnail is None else photometric_change(state.thumbnail, thumb)
    state.thumbnail = thumb
    if prev is None or prev.shape != left.shape[:2] or state.scale is None or change > SCENE_CUT:
        if prev is not None and prev.shape == left.shape[:2]:
            logger.info("scene cut (photometric change %.3f > %.2f): a new sequence starts", change, SCENE_CUT)
        result = run(model, left, right, model_inference_config(model, iters, scale, refine), device, amp)
        state.disparity, state.scale = result.disparity, result.input_scale
        return result.disparity
    refine = model_inference_config(model, refine=refine).refine
    disp = pass_at_scale(model, left, right, state.scale, np.nan_to_num(prev, nan=0.0).astype(np.float32),
                         sequence_iters, device, amp)
    state.disparity = apply_refine(disp, left, refine, device)
    return state.disparity


def infer_sequence(model: nn.Module, frames: Iterable[tuple[Image, Image]], **kwargs) -> Iterator[Disparity]:
    """Disparities of an ordered iterable of (left, right) frames (:func:`infer_next`'s keyword arguments); a frame
    of another size than the one before, or after a scene cut, restarts the sequence from the plain path."""
    state = SequenceState()
    for left, right in frames:
        yield infer_next(model, left, right, state, **kwargs)


def _flow(source: Image, target: Image) -> npt.NDArray[np.float32]:
    """(H, W, 2) dense optical flow (OpenCV DIS, medium preset) from ``source`` to ``target`` (H, W, 3) uint8."""
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    grey = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in (source, target)]
    return dis.calc(grey[0], grey[1], None).astype(np.float32)


def _remap(image: np.ndarray, flow: npt.NDArray[np.float32], nearest: bool = False) -> np.ndarray:
    h, w = flow.shape[:2]
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    return cv2.remap(image, xs + flow[..., 0], ys + flow[..., 1], interp, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=np.nan if image.dtype == np.float32 else 0)


def followable(prev_left: Image, left: Image) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.float32]]:
    """Where a pixel of ``left`` (frame t) can be followed back into ``prev_left`` (frame t - 1), and the flow.

    Returns (mask (H, W) bool, flow (H, W, 2) float32 from t to t - 1). A pixel is kept when it lands inside frame
    t - 1, the backward flow there leads back within FLOW_TOLERANCE px, and the warped previous image matches the
    current one within PHOTO_TOLERANCE (mean |RGB| / 255).
    """
    back = _flow(left, prev_left)
    fwd = _flow(prev_left, left)
    fwd_at = _remap(fwd, back)
    loop = np.linalg.norm(back + fwd_at, axis=2)
    warped = _remap(prev_left.astype(np.float32), back)
    photo = np.abs(warped - left.astype(np.float32)).mean(axis=2) / 255.0
    h, w = left.shape[:2]
    xs, ys = np.meshgrid(np.arange(w), np.arange(h))
    inside = (xs + back[..., 0] >= 0) & (xs + back[..., 0] <= w - 1) & (ys + back[..., 1] >= 0) & (
        ys + back[..., 1] <= h - 1)
    return inside & (loop < FLOW_TOLERANCE) & (photo < PHOTO_TOLERANCE), back


def temporal_change(prev_left: Image, left: Image, prev_disp: Disparity, disp: Disparity) -> tuple[float, float]:
    """(mean |d_t - d_{t-1} warped to t| in px, fraction of pixels measured) on :func:`followable` pixels where both
    disparities are finite and positive. The warp follows the left images' optical flow; a disparity's true change
    under the camera's motion is part of the number, the same for any two methods compared on the same frames."""
    mask, back = followable(prev_left, left)
    prev_at = _remap(prev_disp.astype(np.float32), back, nearest=True)
    ok = mask & np.isfinite(prev_at) & np.isfinite(disp) & (prev_at > 0) & (disp > 0)
    if not ok.any():
        return float("nan"), 0.0
    return float(np.abs(disp[ok] - prev_at[ok]).mean()), float(ok.mean())
