"""``optstereo-predict``: disparity files (KITTI PNG, PFM, NPY, colour, depth, confidence) of a pair or a dataset."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import click
import torch

from optstereo.checkpoint import model_inference
from optstereo.choices import CONF_FORMATS, GEOMETRY_FORMATS, PREDICT_FORMATS, VIDEO_DATASETS
from optstereo.cli import common
from optstereo.export import infer_onnx, onnx_inference_config, onnx_session
from optstereo.geometry import read_calibration
from optstereo.inference import engine as inference
from optstereo.inference import outputs
from optstereo.inference.config import InferenceConfig
from optstereo.inference.predict_more import MoreOptions, frames_of, more_options, predict_frames
from optstereo.submission import submission_problems
from pvm_labeler.common.io import image_size, read_image

logger = logging.getLogger(__name__)


@click.command(cls=common.GuardedCommand, context_settings={"show_default": True})
@click.argument("left", type=common.EXISTING, required=False)
@click.argument("right", type=common.EXISTING, required=False)
@click.option("--checkpoint", type=click.Path(path_type=Path), required=True,
              help="Checkpoint file, RUN_DIR, or 'pretrained' (the shipped model).")
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Output folder.")
@common.dataset_option
@click.option("--root", type=common.EXISTING,
              help="Dataset root (predicts the whole dataset; KITTI: disp_0/<frame>.png).")
@common.reader_options
@click.option("--split", default="training", help="Dataset split.")
@click.option("--limit", type=int, default=None, help="Only the first N frames of --dataset.")
@click.option("--iters", type=int, default=None,
              help="GRU iterations (default: the checkpoint's settings; `pretrained` 3).")
@click.option("--format", "formats", multiple=True, default=("png", "color"),
              type=click.Choice(PREDICT_FORMATS),
              help="Outputs: png = KITTI 16-bit (x256), pfm, npy, color; with --calib (or a --dataset's own "
                   "calib.txt): depth-png (16-bit mm; 0 = none or beyond 65.5 m), depth-pfm / depth-npy (m), ply "
                   "(coloured point cloud), with --min-confidence of its confident pixels only; conf-png (16-bit, "
                   "confidence x 65535) / conf-npy (float32 in [0, 1]) (repeatable).")
@click.option("--calib", type=common.EXISTING,
              help="Rig calibration for depth/PLY: KITTI calib_cam_to_cam.txt, Middlebury calib.txt or a .yaml/.yml "
                   "file (fx, cx, cy, baseline [m], doffs; width, height to have its size checked).")
@click.option("--max-depth", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Drop depths beyond this many metres (depth and PLY; > 0: leave it out for no limit).")
@click.option("--backend", type=click.Choice(("torch", "onnxruntime")), default="torch",
              help="onnxruntime runs an exported .onnx given as --checkpoint (one LEFT RIGHT pair, disparity formats, "
                   "--scale/--refine/--threads; the other options are refused).")
@click.option("--submission", type=click.Path(path_type=Path),
              help="With --dataset kitti15|kitti12: also write this .zip for the KITTI benchmark (its _10 frames "
                   "only; the files checked, and a warning when the server would refuse it).")
@common.device_option
@common.infer_options
@more_options
@click.option("--quiet", is_flag=True, help="Only warnings and errors.")
def predict_main(left: Path | None, right: Path | None, checkpoint: Path, out: Path, dataset: str | None,
                 root: Path | None, split: str, limit: int | None, iters: int | None, formats: tuple[str, ...],
                 calib: Path | None, max_depth: float | None, backend: str, submission: Path | None, device: str,
                 amp: str, scale: float | None, refine: str | None, quiet: bool, sequence: bool,
                 sequence_iters: int, min_confidence: float, color_max: float | None, **reader: Any) -> None:
    """Disparity maps: optstereo-predict --checkpoint CKPT LEFT RIGHT --out DIR (or --dataset NAME --root PATH)."""
    common.setup_logging(quiet)
    if dataset is None and (left is None or right is None):
        raise click.UsageError("give LEFT RIGHT image files, or --dataset NAME --root PATH")
    if left is not None and right is not None and left.is_dir() and right.is_dir():
        raise click.UsageError(f"LEFT and RIGHT are one pair's image files; for folders of pairs give --dataset "
                               f"folder --root {left.parent} --left {left.name} --right {right.name}")
    if dataset is not None and left is not None:
        raise click.UsageError("give either LEFT RIGHT or --dataset, not both")
    if sequence and dataset is not None and dataset not in VIDEO_DATASETS:
        raise click.UsageError(f"--sequence runs the frames of a video, and --dataset {dataset} holds unrelated scenes "
                               f"(one stereo pair each): each would start from another scene's disparity. Leave "
                               f"--sequence out, or give video frames with --dataset {', '.join(VIDEO_DATASETS)}")
    if backend == "onnxruntime":
        _refuse_for_onnx(iters=iters, amp=amp, device=device, sequence=sequence, min_confidence=min_confidence,
                         formats=formats, calib=calib, max_depth=max_depth)
    common.check_out(out)
    if backend == "onnxruntime":
        _predict_onnx(checkpoint, left, right, out, formats, dataset, scale, refine, color_max)
        return
    geometry = [f for f in formats if f in GEOMETRY_FORMATS]
    if geometry and calib is None and dataset is None:
        raise click.UsageError(f"--format {' '.join(geometry)} needs --calib FILE")
    rig = None
    if (calib is not None or max_depth is not None) and not geometry:
        logger.warning("%s read by the depth and point-cloud formats only (--format depth-png, depth-pfm, "
                       "depth-npy, ply): not used", " and ".join(n for n, v in (("--calib", calib),
                                                                         ("--max-depth", max_depth)) if v is not None))
    elif calib is not None:
        rig = read_calibration(calib)
    model, dev = common.load_model(checkpoint, device)
    if sequence:
        _check_sequence(model, checkpoint)
    more = MoreOptions(sequence, sequence_iters, min_confidence, color_max)
    if more.active(formats):  # optstereo.inference.predict_more: --sequence, confidence formats, --min-confidence
        if submission is not None:
            raise click.UsageError("--sequence / conf-* / --min-confidence do not combine with --submission")
        frames = frames_of(left, right, dataset, root, split, limit, common.collect_reader_options(**reader))
        try:
            written = predict_frames(model, frames, out, more, formats=formats, iters=iters, device=dev,
                                     amp=amp, scale=scale, refine=refine, progress=not quiet,
                                     kitti_layout=bool(dataset and dataset.startswith("kitti")), calib=rig,
                                     max_depth=max_depth if max_depth is not None else float("inf"))
        except MemoryError as exc:  # its pre-flight, from the headers: before any frame was run or written
            raise click.ClickException(str(exc)) from exc
        click.echo(f"wrote {_frames(len(written))} into {out}")
        return
    if dataset is None:
        _check_memory(left, right, inference.model_inference_config(model, iters, scale, refine), dev.type)
        paths = outputs.predict_pair(model, left, right, out, iters=iters, formats=formats, device=dev,
                             amp=amp, calib=rig, max_depth=max_depth if max_depth is not None else float("inf"),
                             scale=scale, refine=refine, color_max=color_max)
        click.echo("wrote " + ", ".join(str(p) for p in paths.values()))
    else:
        if submission is not None and "png" not in formats:
            formats = (*formats, "png")
        try:
            written = outputs.predict_dataset(model, dataset, root, out, split=split, iters=iters, formats=formats,
                                              device=dev, limit=limit, amp=amp, submission=submission,
                                              reader_options=common.collect_reader_options(**reader), scale=scale,
                                              refine=refine, progress=not quiet, calib=rig,
                                              max_depth=max_depth if max_depth is not None else float("inf"),
                                              color_max=color_max)
        except MemoryError as exc:  # its pre-flight, from the headers: before any frame was run or written
            raise click.ClickException(str(exc)) from exc
        click.echo(f"wrote {_frames(len(written))} into {out}"
                   + (f"; submission {submission} (its files checked)" if submission is not None else ""))
        if submission is not None:  # predict_dataset ran the _10 frames only
            for problem in submission_problems(dataset, split, len(written)):
                logger.warning("KITTI's server would refuse %s: %s", submission, problem)


def _refuse_for_onnx(*, iters: int | None, amp: str, device: str, sequence: bool, min_confidence: float,
                     formats: tuple[str, ...], calib: Path | None, max_depth: float | None) -> None:
    """Exit 2 naming every option ``--backend onnxruntime`` cannot honour, before anything is loaded or run (it used
    to ignore --iters, --amp and --min-confidence, and to fail on conf-* formats after running)."""
    torch_only = "the torch model's passes"
    unhonoured = [
        (iters is not None, f"--iters {iters} (the graph's GRU iterations are fixed by optstereo-export --iters)"),
        (amp != "none", f"--amp {amp} (onnxruntime runs the graph in float32)"),
        (device == "cuda", "--device cuda (onnxruntime runs on the CPU here)"),
        (sequence, "--sequence (a video of --dataset frames: torch backend)"),
        (min_confidence > 0, f"--min-confidence {min_confidence:g} (the confidence needs {torch_only})"),
        *((True, f"--format {f} (the confidence needs {torch_only})") for f in formats if f in CONF_FORMATS),
        *((True, f"--format {f} (depth and point clouds: torch backend)") for f in formats if f in GEOMETRY_FORMATS),
        (calib is not None, "--calib (depth and point clouds: torch backend)"),
        (max_depth is not None, "--max-depth (depth and point clouds: torch backend)"),
    ]
    named = [text for given, text in unhonoured if given]
    if named:
        raise click.UsageError("--backend onnxruntime cannot honour " + "; ".join(named) + ". Leave them out, or "
                               "run the checkpoint with --backend torch")


def _predict_onnx(onnx_file: Path, left: Path | None, right: Path | None, out: Path, formats: tuple[str, ...],
                  dataset: str | None, scale: float | None, refine: str | None, color_max: float | None) -> None:
    if dataset is not None or left is None or right is None or Path(onnx_file).suffix != ".onnx":
        raise click.UsageError("--backend onnxruntime takes an exported .onnx as --checkpoint and one LEFT RIGHT pair")
    if not Path(onnx_file).is_file():
        raise click.BadParameter(f"{onnx_file} does not exist", param_hint="--checkpoint")
    session = onnx_session(onnx_file, threads=torch.get_num_threads())  # --threads, or one per core
    config = onnx_inference_config(session)
    _check_memory(left, right, config if scale is None else config.fixed(scale), "cpu")
    disp = infer_onnx(session, read_image(left), read_image(right), scale=scale, refine=refine)
    paths = outputs.write_disparity(out, Path(left).stem, disp, formats, max_disp=color_max)
    click.echo("wrote " + ", ".join(str(p) for p in paths.values()))


def _check_memory(left: Path, right: Path, config: InferenceConfig, device_type: str) -> None:
    """Exit 1 naming LEFT when the pair's estimated peak memory at ``config``'s first scale exceeds the free memory
    (``outputs.check_pairs_fit``); read from the image headers, before either image is decoded. Pairs of different
    sizes are refused here too."""
    size = image_size(left)
    if image_size(right) != size:
        raise click.ClickException(f"left/right sizes differ: {size} vs {image_size(right)}: {left}, {right}")
    try:
        outputs.check_pairs_fit(config, [left], device_type == "cuda")
    except MemoryError as exc:
        raise click.ClickException(str(exc)) from exc


def _frames(n: int) -> str:
    """"1 frame", "2 frames"."""
    return f"{n} frame{'' if n == 1 else 's'}"


def _check_sequence(model: Any, checkpoint: Path) -> None:
    """--sequence starts every frame after the first from the frame before: refused (exit 2, before any frame is
    read) for a model whose own settings never start its GRU from a disparity (no coarse start), i.e. one trained
    from a zero start only. Measured on drive 2011_09_26_0001 (results/sequence/): `pretrained` started so reads
    bad-3 3.5 % against the drive's PVM labels where its independent frames read 0.08 %, at the same time."""
    if not model_inference(model).coarse_start:
        raise click.UsageError(
            f"--sequence starts each frame's GRU from the frame before, and {checkpoint} was trained from a zero "
            "start only: started frames come out worse (`pretrained` on a KITTI drive: 3.5 % of pixels over 3 px "
            "from the PVM labels against 0.08 % independently) and no faster (results/sequence/). Leave --sequence "
            "out, or use a model trained with starts (`--checkpoint pretrained-accurate`)")
