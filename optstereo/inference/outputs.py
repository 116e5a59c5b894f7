"""Disparity files in the field's formats, and ``optstereo-predict``'s loops over pairs and datasets.

Outputs per frame (``formats`` picks them): ``png`` KITTI 16-bit PNG (disparity x 256, 0 = invalid), ``pfm``
(float32, Middlebury/Scene Flow), ``npy`` (float32), ``color`` (8-bit colour rendering for people). The KITTI form
(``kitti_layout=True``) names files as the benchmark's submission expects: ``disp_0/<frame>_10.png``. The disparity
itself comes from ``optstereo.inference.engine.infer`` (the one inference path).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from torch import nn
from tqdm import tqdm

from optstereo.choices import CONF_FORMATS, DISPARITY_FORMATS, GEOMETRY_FORMATS
from optstereo.geometry import depth_to_points, disparity_to_depth, read_calibration, write_depth_png, write_ply
from optstereo.inference.confidence import confidence_paths
from optstereo.inference.config import InferenceConfig
from optstereo.inference.engine import first_scale, infer, model_inference_config
from optstereo.memory import check_fits
from optstereo.submission import write_submission
from pvm_labeler.common.atomic import record_failures
from pvm_labeler.common.datasets import discover, load_pair, safe_stem
from pvm_labeler.common.errors import ConfigError, InputError, PVMError, counted
from pvm_labeler.common.io import (
    KITTI_SCALE,
    image_size,
    read_image,
    write_disparity_file,
    write_image,
    write_npy,
    write_pfm,
)
from pvm_labeler.common.viz import colorize_disparity

logger = logging.getLogger(__name__)

DEFAULT_FORMATS = ("png", "color")


def colorize(disp: npt.NDArray[np.float32], max_disp: float | None = None) -> npt.NDArray[np.uint8]:
    """(H, W, 3) uint8 colour rendering of a disparity map (NaN = black), via the labeler's viz module."""
    return colorize_disparity(disp, max_disp=max_disp)


def write_disparity(
    out_dir: Path, name: str, disp: npt.NDArray[np.float32], formats: Iterable[str] = DEFAULT_FORMATS,
    *, kitti_layout: bool = False, max_disp: float | None = None,
) -> dict[str, Path]:
    """Write one disparity map in the requested formats; returns format -> path.

    With ``kitti_layout`` the 16-bit PNG goes to ``out_dir/disp_0/<name>.png`` (the KITTI submission layout;
    ``name`` is then the frame's file stem such as ``000000_10``) and the others into sibling folders. A ``name`` that
    is no plain file name (``../x``: a shard's frame id) is made one (``pvm_labeler.common.datasets.safe_stem``).
    The network's map is dense: in the 16-bit PNG, where 0 means "no value", a prediction at or just below 0 px
    (sky, -0.02 px) is written as the smallest value, 1/256 px (PFM and ``.npy`` keep it as predicted).
    """
    paths = disparity_paths(out_dir, name, formats, kitti_layout=kitti_layout)
    for fmt, path in paths.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        if fmt == "color":
            write_image(path, colorize(disp, max_disp))
        elif fmt == "png":
            write_disparity_file(path, dense_for_png(disp))
        else:
            write_disparity_file(path, disp)
    return paths


def dense_for_png(disp: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
    """(H, W) float32: finite values floored at 1/256 px (the KITTI PNG's smallest valid code); NaN stays NaN."""
    disp = np.asarray(disp, dtype=np.float32)
    return np.where(np.isfinite(disp), np.maximum(disp, np.float32(1 / KITTI_SCALE)), disp)


def disparity_paths(out_dir: Path, name: str, formats: Iterable[str] = DEFAULT_FORMATS, *,
                    kitti_layout: bool = False) -> dict[str, Path]:
    """format -> the file :func:`write_disparity` writes for frame ``name`` (geometry formats left out)."""
    name = safe_stem(name)
    formats = tuple(f for f in formats if f not in GEOMETRY_FORMATS)
    unknown = sorted(set(formats) - set(DISPARITY_FORMATS))
    if unknown:
        raise ValueError(f"unknown output formats {unknown}; choose from {DISPARITY_FORMATS}")
    folders = {"png": "disp_0", "pfm": "pfm", "npy": "npy", "color": "color"} if kitti_layout else {}
    return {fmt: Path(out_dir) / folders.get(fmt, "") / (f"{name}_color.png" if fmt == "color" else f"{name}.{fmt}")
            for fmt in formats}


#: The file of each geometry format, by frame name (in ``out_dir`` itself).
GEOMETRY_NAMES = {"depth-png": "{name}_depth.png", "depth-pfm": "{name}_depth.pfm", "depth-npy": "{name}_depth.npy",
                  "ply": "{name}.ply"}


def output_paths(out_dir: Path, name: str, formats: Iterable[str], kitti_layout: bool = False) -> dict[str, Path]:
    """format -> the file optstereo-predict writes for frame ``name``, every kind (disparity, confidence: in
    ``conf/`` in the KITTI layout, geometry)."""
    formats = tuple(formats)
    out_dir = Path(out_dir)
    return {**disparity_paths(out_dir, name, [f for f in formats if f not in CONF_FORMATS], kitti_layout=kitti_layout),
            **confidence_paths(out_dir / ("conf" if kitti_layout else ""), name, formats),
            **{f: out_dir / GEOMETRY_NAMES[f].format(name=safe_stem(name)) for f in formats if f in GEOMETRY_NAMES}}


def refuse_overwriting_inputs(out_dir: Path, frames: Iterable[tuple[str, Path, Path]], formats: Iterable[str],
                              kitti_layout: bool = False) -> None:
    """ConfigError naming the first input image that an output of (name, left, right) ``frames`` would replace
    (``--out`` the images' own folder: ``<left stem>.png`` is the left image), before anything is run or written."""
    frames = list(frames)
    inputs = {Path(p).resolve() for _, left, right in frames for p in (left, right)}
    formats = tuple(formats)
    for name, _, _ in frames:
        for fmt, path in output_paths(out_dir, name, formats, kitti_layout).items():
            if path.resolve() in inputs:
                raise ConfigError(f"the {fmt} output of {name} would overwrite the input image {path}: give an "
                                  "--out folder other than the images' own")


def forget_frame(out_dir: Path, name: str, formats: Iterable[str], kitti_layout: bool = False) -> None:
    """Remove an earlier run's files of frame ``name`` in ``out_dir`` (every kind: :func:`output_paths`): a frame
    that failed now must not leave an old answer beside this run's (failures.json lists it)."""
    for path in output_paths(out_dir, name, formats, kitti_layout).values():
        path.unlink(missing_ok=True)


def write_geometry(
    out_dir: Path, name: str, disp: npt.NDArray[np.float32], image: npt.NDArray[np.uint8], calib: Any,
    formats: Iterable[str], max_depth: float = float("inf"),
) -> dict[str, Path]:
    """Depth (16-bit mm PNG, PFM/NPY in m) and a coloured PLY point cloud of one prediction; format -> path."""
    wanted = [f for f in formats if f in GEOMETRY_FORMATS]
    if not wanted:
        return {}
    if calib is None:
        raise ValueError(f"formats {wanted} need a calibration: pass --calib FILE")
    calib.check_fits(*disp.shape)
    depth = disparity_to_depth(disp, calib, max_depth)
    name = safe_stem(name)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {fmt: out_dir / GEOMETRY_NAMES[fmt].format(name=name) for fmt in wanted}
    for fmt, path in paths.items():
        if fmt == "depth-png":
            write_depth_png(path, depth)
        elif fmt == "depth-pfm":
            write_pfm(path, depth)
        elif fmt == "depth-npy":
            write_npy(path, depth)
        else:
            write_ply(path, *depth_to_points(depth, calib, image))
    return paths


def predict_pair(
    model: nn.Module, left_path: Path, right_path: Path, out_dir: Path, *, iters: int | None = None,
    formats: Iterable[str] = DEFAULT_FORMATS, device: torch.device | str = "cpu", amp: str = "none",
    calib: Any = None, max_depth: float = float("inf"), scale: float | None = None, refine: str | None = None,
    color_max: float | None = None,
) -> dict[str, Path]:
    """Predict one pair from image files and write ``<left stem>.<ext>`` files into out_dir (depth/PLY: ``calib``;
    the ``color`` picture's top at ``color_max`` px, None = the map's own largest value)."""
    refuse_overwriting_inputs(out_dir, [(Path(left_path).stem, left_path, right_path)], formats)
    if calib is not None and any(f in GEOMETRY_FORMATS for f in formats):
        calib.check_fits(*image_size(left_path))  # before the network runs, not after
    left, right = read_image(left_path), read_image(right_path)
    if left.shape != right.shape:
        raise ValueError(f"left/right sizes differ: {left.shape[:2]} vs {right.shape[:2]}: {left_path}, {right_path}")
    t0 = time.perf_counter()
    disp = infer(model, left, right, iters=iters, device=device, amp=amp, scale=scale, refine=refine)
    logger.info("%s: %.2f s", left_path, time.perf_counter() - t0)
    stem = Path(left_path).stem
    return {**write_disparity(out_dir, stem, disp, formats, max_disp=color_max),
            **write_geometry(out_dir, stem, disp, left, calib, formats, max_depth)}


def check_pairs_fit(config: InferenceConfig, lefts: Iterable[Path], cuda: bool = False,
                    available: float | None = None) -> None:
    """Raise MemoryError naming the first left image whose pair would not fit in the free memory (``available``
    bytes, None = ask the system) at the first scale ``config`` gives it (``engine.first_scale``); from the image
    headers alone, before any pair is decoded or any output written. A file whose header cannot be read is passed
    over: the loop that reads it skips and lists it (it stopped the whole run here)."""
    for left in lefts:
        try:
            size = image_size(left)
        except InputError:
            continue
        check_fits(str(left), *size, scale=first_scale(config, size), cuda=cuda, available=available)


def pair_calibrations(calib: Any, pairs: Iterable[tuple[str, Path, str | None]]) -> dict[str, Any]:
    """{frame id: calibration} for the depth and point-cloud formats of (frame id, left image, the pair's own
    calibration file or None) ``pairs``: its own (a Middlebury or ETH3D scene's calib.txt, which differ from scene to
    scene) where it has one, else ``calib`` (``--calib``). Each is checked against the pair's image size from the
    headers, once per calibration and size (an unreadable header is passed over: the loop skips and lists the pair).
    ConfigError naming the pairs with neither."""
    pairs = list(pairs)
    own = {name: read_calibration(path) for name, _, path in pairs if path}
    missing = [name for name, _, _ in pairs if name not in own and calib is None]
    if missing:
        raise ConfigError(f"the depth and point-cloud formats need a calibration: {counted(len(missing), 'pair')} "
                          f"({', '.join(missing[:3])}{' ...' if len(missing) > 3 else ''}) have none of their own: "
                          "pass --calib FILE")
    if own and calib is not None:
        logger.info("%s use their own calib.txt; --calib %s serves the others", counted(len(own), "pair"),
                    calib.source)
    calibs = {name: own.get(name, calib) for name, _, _ in pairs}
    checked = set()  # its warning is not repeated for every pair
    for name, left, _ in pairs:
        try:
            size = image_size(left)
        except InputError:
            continue
        if (id(calibs[name]), size) not in checked:
            calibs[name].check_fits(*size)
            checked.add((id(calibs[name]), size))
    return calibs


def predict_dataset(
    model: nn.Module, dataset: str, root: Path | None, out_dir: Path, *, split: str = "training",
    iters: int | None = None, formats: Iterable[str] = DEFAULT_FORMATS, device: torch.device | str = "cpu",
    limit: int | None = None, amp: str = "none", submission: Path | None = None,
    reader_options: dict[str, Any] | None = None, scale: float | None = None, refine: str | None = None,
    progress: bool = False, calib: Any = None, max_depth: float = float("inf"), color_max: float | None = None,
) -> list[dict[str, Path]]:
    """Predict every pair of a dataset (``progress``: a progress bar); KITTI datasets get the submission layout
    ``disp_0/<frame>_10.png``. Depth and PLY formats use each pair's own calibration where the dataset has one
    (Middlebury, ETH3D), else ``calib`` (:func:`pair_calibrations`; checked against each image size first).

    With ``submission`` only the ``_10`` frames are run (``limit`` counts them) and zipped (and checked) for the
    KITTI benchmark server. Every pair's memory need is checked from its image headers before the first is run
    (:func:`check_pairs_fit`), and that no output would replace an input image. A pair that cannot be read (a corrupt
    or truncated image) is skipped and the others are written; then ``OUT/failures.json`` lists each with its reason
    and an InputError names the first (no submission is written then).
    """
    refs = discover(dataset, root, split=split, **(reader_options or {}))
    formats = tuple(formats)
    if submission is not None and not dataset.startswith("kitti"):
        raise ConfigError(f"--submission writes the KITTI benchmark layout; dataset {dataset!r} is not KITTI")
    if submission is not None:  # the benchmark scores the reference frames: the _11 pairs are not run (nor counted)
        refs = [ref for ref in refs if ref.frame_id.endswith("_10")]
    refs = refs[:limit]
    check_pairs_fit(model_inference_config(model, iters, scale, refine), [Path(ref.left) for ref in refs],
                    torch.device(device).type == "cuda")
    kitti_layout = dataset.startswith("kitti")
    calibs = (pair_calibrations(calib, [(ref.frame_id, Path(ref.left), ref.meta.get("calib")) for ref in refs])
              if any(f in GEOMETRY_FORMATS for f in formats) else {})
    refuse_overwriting_inputs(out_dir, [(ref.frame_id, ref.left, ref.right) for ref in refs], formats, kitti_layout)
    written, failed = [], {}
    # disable=None: tqdm's bar is off on a stream that is no terminal (a piped log)
    for ref in tqdm(refs, desc="predict", unit="pair", disable=None if progress else True):
        try:
            sample = load_pair(ref)
        except PVMError as exc:
            logger.warning("skipped %s: %s", ref.frame_id, exc)
            failed[ref.frame_id] = str(exc)
            forget_frame(Path(out_dir), ref.frame_id, formats, kitti_layout=kitti_layout)
            continue
        disp = infer(model, sample.left, sample.right, iters=iters, device=device, amp=amp, scale=scale,
                     refine=refine)
        written.append({**write_disparity(out_dir, ref.frame_id, disp, formats, kitti_layout=kitti_layout,
                                          max_disp=color_max),
                        **write_geometry(out_dir, ref.frame_id, disp, sample.left, calibs.get(ref.frame_id), formats,
                                         max_depth)})
    record_failures(Path(out_dir), failed, len(refs))
    if submission is not None:
        write_submission(out_dir, submission, refs)
    return written

