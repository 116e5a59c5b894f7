"""``optstereo-predict``'s video and confidence outputs: ``--sequence``, ``--format conf-png|conf-npy`` and
``--min-confidence``, a per-frame loop beside ``optstereo.inference.engine.predict_dataset`` that writes the same files.

Options (click decorators) live here too, so that the predict command gains them in one line.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click
import numpy as np
import numpy.typing as npt
import torch
from torch import nn
from tqdm import tqdm

from optstereo.choices import CONF_FORMATS, GEOMETRY_FORMATS
from optstereo.inference.confidence import confidence_of, write_confidence
from optstereo.inference.engine import model_inference_config, run
from optstereo.inference.outputs import (
    check_pairs_fit,
    forget_frame,
    pair_calibrations,
    refuse_overwriting_inputs,
    write_disparity,
    write_geometry,
)
from optstereo.inference.sequence import DEFAULT_SEQUENCE_ITERS, SequenceState, infer_next, natural_key
from pvm_labeler.common.atomic import record_failures
from pvm_labeler.common.datasets import discover
from pvm_labeler.common.errors import InputError, PVMError
from pvm_labeler.common.io import read_image

logger = logging.getLogger(__name__)



@dataclass(frozen=True)
class MoreOptions:
    """What the loop does beyond the plain path: sequence starts, confidence files, a semi-dense cut."""

    sequence: bool = False
    sequence_iters: int = DEFAULT_SEQUENCE_ITERS
    min_confidence: float = 0.0
    color_max: float | None = None  # the ``color`` picture's top (px); None: each frame's own largest value

    def active(self, formats: Iterable[str]) -> bool:
        """True when the plain path (``predict_pair`` / ``predict_dataset``) cannot serve the request."""
        return self.sequence or self.min_confidence > 0 or any(f in CONF_FORMATS for f in formats)


def more_options(fn):
    """--sequence, --sequence-iters, --min-confidence and --color-max for optstereo-predict."""
    fn = click.option("--color-max", type=click.FloatRange(min=0, min_open=True), default=None,
                      help="Disparity (px) at the top of the `color` picture's scale, the same for every frame (a "
                           "video's colours no longer change with each frame's largest value).  [default: each "
                           "frame's own largest value]")(fn)
    fn = click.option("--min-confidence", type=click.FloatRange(0, 1), default=0.0,
                      help="Semi-dense output: pixels whose confidence (optstereo.inference.confidence) is below "
                           "this get no value (0 in png, inf in pfm as Middlebury's, NaN in npy). 0 = dense.")(fn)
    fn = click.option("--sequence-iters", type=click.IntRange(min=1), default=DEFAULT_SEQUENCE_ITERS,
                      help="--sequence: GRU iterations of every frame after the first.")(fn)
    return click.option("--sequence", is_flag=True,
                        help="--dataset frames (folder, kitti_unlabelled, sceneflow) are a video in frame-name order "
                             "(frame_2 before frame_10): each frame's GRU starts from the previous frame's answer with "
                             "--sequence-iters iterations; the first frame, a frame of another folder or size, and a "
                             "scene cut run the plain path. Only for models trained with such starts "
                             "(pretrained-accurate); refused for one trained from a zero start (pretrained).")(fn)


def predict_frames(model: nn.Module, frames: Iterable[tuple[str, Path, Path]], out_dir: Path, more: MoreOptions, *,
                   formats: Iterable[str], kitti_layout: bool = False, iters: int | None = None,
                   device: torch.device | str = "cpu", amp: str = "none", scale: float | None = None,
                   refine: str | None = None, progress: bool = True, calib: Any = None,
                   max_depth: float = float("inf")) -> list[dict[str, Path]]:
    """Predict (name, left path, right path) frames in order and write each one's files; returns format -> path
    per frame. With ``more.sequence`` the frames run in the natural order of their names
    (``optstereo.inference.sequence.natural_key``: ``frame_2`` before ``frame_10``) and each frame after the first
    starts from the one before (optstereo.inference.sequence); a frame that cannot be read is skipped (its earlier
    files removed) and listed in ``out_dir/failures.json``, then InputError names it; a frame from another folder than
    the one before
    (another drive of ``kitti_unlabelled``), of another size, or after a scene cut starts a new sequence. MemoryError
    naming the first pair that would not fit, from the image headers, before any frame is run or written (the
    confidence's second pass is no larger). Depth and PLY formats use ``calib`` (one rig's, checked against every
    image size first) on the disparity as written: with ``--min-confidence``, its confident pixels only."""
    formats = tuple(formats)
    frames = sorted(frames, key=lambda frame: natural_key(frame[0])) if more.sequence else list(frames)
    state, folder = SequenceState(), None
    config = model_inference_config(model, iters, scale, refine)  # the same for every frame
    check_pairs_fit(config, [Path(frame[1]) for frame in frames], torch.device(device).type == "cuda")
    refuse_overwriting_inputs(out_dir, frames, formats, kitti_layout)
    calibs = (pair_calibrations(calib, [(name, Path(left), None) for name, left, _ in frames])
              if any(f in GEOMETRY_FORMATS for f in formats) else {})
    written, failed = [], {}
    # disable=None: tqdm's bar is off on a stream that is no terminal (a piped log)
    for name, left_path, right_path in tqdm(frames, desc="predict", unit="frame", disable=None if progress else True):
        if Path(left_path).parent != folder:
            state, folder = SequenceState(), Path(left_path).parent
        try:
            left, right = read_image(left_path), read_image(right_path)
            if left.shape != right.shape:
                raise InputError(f"left/right sizes differ: {left.shape[:2]} vs {right.shape[:2]}: {left_path}, "
                                 f"{right_path}")
        except PVMError as exc:  # skipped and listed; a sequence starts afresh after the gap
            if len(frames) == 1:  # one pair given as files: its own error
                raise
            logger.warning("skipped %s: %s", name, exc)
            failed[name] = str(exc)
            forget_frame(Path(out_dir), name, formats, kitti_layout)
            state = SequenceState()
            continue
        t0 = time.perf_counter()
        if more.sequence:
            disp = infer_next(model, left, right, state, iters=iters, sequence_iters=more.sequence_iters,
                              device=device, amp=amp, scale=scale, refine=refine)
            used_scale = state.scale
        else:
            result = run(model, left, right, config, device, amp)
            disp, used_scale = result.disparity, result.input_scale
        conf = _confidence(model, left, right, disp, more, formats, device, amp, used_scale, config.iters)
        logger.info("%s: %.2f s", name, time.perf_counter() - t0)
        shown = _confident(disp, conf, more)  # what the disparity files, depth and cloud hold
        written.append({**_write(out_dir, name, shown, conf, more, formats, kitti_layout),
                        **write_geometry(out_dir, name, shown, left, calibs.get(name), formats, max_depth)})
    if len(frames) > 1:
        record_failures(Path(out_dir), failed, len(frames))
    return written


def _confidence(model: nn.Module, left: np.ndarray, right: np.ndarray, disp: npt.NDArray[np.float32],
                more: MoreOptions, formats: tuple[str, ...], device: torch.device | str,
                amp: str, scale: float, iters: int | None) -> npt.NDArray[np.float32] | None:
    """The disparity's confidence when a format or --min-confidence asks for it; the LR pass runs at ``scale``, the
    input scale of the pass that made ``disp``, and the settings' ``iters`` (as
    ``confidence.infer_with_confidence`` does)."""
    if more.min_confidence <= 0 and not any(f in CONF_FORMATS for f in formats):
        return None
    return confidence_of(model, left, right, disp, device=device, amp=amp, scale=scale, iters=iters)


def _confident(disp: npt.NDArray[np.float32], conf: npt.NDArray[np.float32] | None,
               more: MoreOptions) -> npt.NDArray[np.float32]:
    """(H, W) float32: ``disp`` with NaN where ``conf`` is under ``--min-confidence`` (as given without it)."""
    if conf is None or more.min_confidence <= 0:
        return disp
    return np.where(conf >= more.min_confidence, disp, np.nan).astype(np.float32)


def _write(out_dir: Path, name: str, disp: npt.NDArray[np.float32], conf: npt.NDArray[np.float32] | None,
           more: MoreOptions, formats: tuple[str, ...], kitti_layout: bool) -> dict[str, Path]:
    """The disparity files of ``disp`` (already cut by --min-confidence: :func:`_confident`) and the confidence's."""
    paths = write_disparity(out_dir, name, disp, [f for f in formats if f not in CONF_FORMATS],
                            kitti_layout=kitti_layout, max_disp=more.color_max)
    if conf is not None:
        paths.update(write_confidence(Path(out_dir) / ("conf" if kitti_layout else ""), name, conf,
                                      [f for f in formats if f in CONF_FORMATS]))
    return paths


def frames_of(left: Path | None, right: Path | None, dataset: str | None, root: Path | None, split: str,
              limit: int | None, reader_options: dict[str, Any]) -> list[tuple[str, Path, Path]]:
    """(name, left, right) of the one given pair, or of the dataset's pairs in frame-id order."""
    if dataset is None:
        assert left is not None and right is not None
        return [(Path(left).stem, Path(left), Path(right))]
    refs = discover(dataset, root, split=split, **reader_options)[:limit]
    return [(ref.frame_id, Path(ref.left), Path(ref.right)) for ref in refs]
