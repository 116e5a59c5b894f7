"""The one home of every choice list of OptStereo's settings and flags (no torch, no I/O, imports nothing of
optstereo, so the configs, the network and the CLI all import it without cycles).

Each list is a ``Literal`` type (for the typed config fields) and the runtime tuple of its values from
``typing.get_args`` (for validation messages and ``click.Choice``). A list defined anywhere else is a duplicate.
"""

from __future__ import annotations

from typing import Literal, get_args

__all__ = [
    "AMP_MODES", "COLOR_NORMS", "CONF_FORMATS", "DEVICES", "DISPARITY_FORMATS", "EXPORT_FORMATS", "GEOMETRY_FORMATS",
    "PREDICT_FORMATS", "NORMS", "PHOTOMETRIC_ITERS", "REFINERS", "SCHEDULES", "SMOOTHNESS_NORMS", "SMOOTHNESS_ORDERS",
    "STAGES", "SUPERVISIONS", "UPSAMPLERS", "VIDEO_DATASETS", "AmpMode", "ColorNorm", "ConfFormat", "Device",
    "DisparityFormat", "ExportFormat", "GeometryFormat", "Norm", "PhotometricIters", "Refiner", "Schedule",
    "SmoothnessNorm", "SmoothnessOrder", "Stage", "Supervision", "Upsampler", "VideoDataset",
]

#: Precision of a forward pass (training's --amp and inference's): fp32, bfloat16 or float16 autocast.
AmpMode = Literal["none", "bf16", "fp16"]
AMP_MODES: tuple[str, ...] = get_args(AmpMode)
#: Where a command runs; "auto" = cuda when available.
Device = Literal["auto", "cpu", "cuda"]
DEVICES: tuple[str, ...] = get_args(Device)
#: Post-filters ``optstereo.inference.engine.run`` can apply to the disparity at the input's size ("wmedian":
#: ``pvm_labeler.refine``).
Refiner = Literal["none", "wmedian"]
REFINERS: tuple[str, ...] = get_args(Refiner)

# -- the network (ModelConfig) ------------------------------------------------------------------------------------
Upsampler = Literal["conv", "convex"]
UPSAMPLERS: tuple[str, ...] = get_args(Upsampler)
Norm = Literal["instance", "batch", "group", "none"]
NORMS: tuple[str, ...] = get_args(Norm)
#: An encoder stage (``stage1`` at 1/2 resolution, ``stage2`` at 1/4): RAFT's two residual blocks, or two
#: depthwise-separable ones.
Stage = Literal["residual", "separable"]
STAGES: tuple[str, ...] = get_args(Stage)

# -- training (LossConfig, DataConfig, OptimConfig) ---------------------------------------------------------------
PhotometricIters = Literal["last", "all"]
PHOTOMETRIC_ITERS: tuple[str, ...] = get_args(PhotometricIters)
SmoothnessNorm = Literal["none", "mean"]
SMOOTHNESS_NORMS: tuple[str, ...] = get_args(SmoothnessNorm)
SmoothnessOrder = Literal[1, 2]
SMOOTHNESS_ORDERS: tuple[int, ...] = get_args(SmoothnessOrder)
ColorNorm = Literal["l1", "mean"]
COLOR_NORMS: tuple[str, ...] = get_args(ColorNorm)
Supervision = Literal["pvm", "gt"]
SUPERVISIONS: tuple[str, ...] = get_args(Supervision)
Schedule = Literal["constant", "onecycle"]
SCHEDULES: tuple[str, ...] = get_args(Schedule)

# -- output files (optstereo-predict --format) -----------------------------------------------------------------
#: Disparity files (``optstereo.inference.outputs.write_disparity``).
DisparityFormat = Literal["png", "pfm", "npy", "color"]
DISPARITY_FORMATS: tuple[str, ...] = get_args(DisparityFormat)
#: Depth and point clouds; they need a calibration (``optstereo.geometry``).
GeometryFormat = Literal["depth-png", "depth-pfm", "depth-npy", "ply"]
GEOMETRY_FORMATS: tuple[str, ...] = get_args(GeometryFormat)
#: Confidence maps (``optstereo.inference.predict_more``).
ConfFormat = Literal["conf-png", "conf-npy"]
CONF_FORMATS: tuple[str, ...] = get_args(ConfFormat)
#: Every value of optstereo-predict's --format.
PREDICT_FORMATS: tuple[str, ...] = DISPARITY_FORMATS + GEOMETRY_FORMATS + CONF_FORMATS

#: ``--dataset`` readers whose frames are videos, which ``optstereo-predict --sequence`` takes; the others
#: (kitti15, kitti12, middlebury, sample) hold unrelated scenes, one stereo pair each.
VideoDataset = Literal["folder", "kitti_unlabelled", "sceneflow"]
VIDEO_DATASETS: tuple[str, ...] = get_args(VideoDataset)

# -- export ---------------------------------------------------------------------------------------------------------
ExportFormat = Literal["onnx", "torchscript"]
EXPORT_FORMATS: tuple[str, ...] = get_args(ExportFormat)
