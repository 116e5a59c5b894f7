"""Export the inference graph (``optstereo-export``) and run it with onnxruntime.

The exported graph is the test-mode network: N_s GRU iterations unrolled, the final full-resolution disparity out.

    inputs   left, right: (1, 3, H, W) float32 in [0, 255], RGB; H and W multiples of 8 (dynamic). Padding to a
             multiple of 8 stays OUTSIDE the graph: :func:`infer_onnx` pads like ``optstereo.inference.engine.infer``
             (replicate padding, then crops the output back). ``batch=True`` exports a dynamic batch (B, 3, H, W)
             instead, at some speed: the default graph runs the feature encoder and the upsampler one image per
             call, as eager torch does on CPU, which makes onnxruntime ~10 % faster at KITTI size (`make bench`).
    output   disparity: (B, 1, H, W) float32, positive, left(x) matches right(x - d).

ONNX: torch's dynamo exporter at opset 18 (``optimize=False``: the graph optimiser of onnxscript 0.7 fails on this
graph; onnxruntime optimises it at load time anyway). TorchScript: ``torch.jit.trace`` of the same wrapper. The ONNX
file's metadata records the model's InferenceConfig (key ``inference_config``, JSON), and :func:`infer_onnx` runs
the graph through ``optstereo.inference.engine.run`` with it, the same sequence as the torch model's (resize, pad,
passes,
unpad, resize back, post-filter); files written before that key read the old per-key metadata (``input_scale``,
``refine``, ``scale_ref_disp``/``scale_ref_pixels``, ``cascade_select``/``cascade_select_jump``). A TorchScript
file records it as the extra file ``inference_config.json`` (``torch.jit.load(f, _extra_files=
{"inference_config.json": ""})``); its caller runs those settings itself (the graph is one pass on a padded
pair). A model with ``InferenceConfig.coarse_start`` exports a graph with a third input, ``start`` (1, 1, H, W): a
full-resolution disparity of the padded pair, zeros for the zero start, which the graph averages onto the 1/8 grid
(``optstereo.inference.cascade.grid_start``).

Speed (`make bench`, section "export": onnxruntime / eager torch on a KITTI frame, 2 threads, alternating):
0.75-0.85x over the runs so far on an AVX-512 Xeon (three back-to-back runs on 2026-11-24: 0.85, 0.83, 0.81;
later 0.81 with 9 repeats, whose paired per-repeat ratios spread from 0.75 to 0.97: the target sits inside the noise).
On AMD EPYCs with AVX-512 and AVX512-BF16: 0.67 on a quiet one (paired 0.47-0.71; torch 0.93 s, onnxruntime
0.62 s), then 0.80 and 0.77 on a slower one the next day (torch 1.68 / 1.60 s; paired 0.64-0.81 and 0.72-0.80).
On an Intel Xeon with AMX, once torch's float32 inference ran the encoder channels-last (0.86x, docs/optstereo.md):
0.94 (torch 1.18 s, onnxruntime 1.11 s, 5 repeats, paired 0.69-1.03; 2026-11-25): a faster torch moves the target.
With version 9, whose input scale is 1.625 (a 609x2018 input), on the same Xeon: 0.73, 0.70 and 0.71 in three runs
(torch 3.5 s, onnxruntime 2.5 s; 0.72 and 0.69 later), and 0.88-1.01 at scale 1 in the same runs (2026-11-26):
for 2.64x the pixels torch's convolutions take 3.0x, its instance norms 3.9x and its elementwise adds 5.3x (torch
profiler), onnxruntime 2.96x.
onnxruntime's profile: Conv + FusedConv 70 %, InstanceNorm 7.5 %, layout reorders 7.7 %, the lookup's gathers 1.4 %.
Tried without a gain beyond the noise: a static shape, InstanceNorm decomposed into reductions, denormals-as-zero,
no thread spinning, the EXTENDED optimisation level, the GRU's z and r convolutions split (fewer layout reorders),
the parallel executor (the two encoder branches side by side, 2 inter-op threads with 1 or 2 intra-op threads each:
1.46-1.54x torch, far slower), and int8 (QDQ, per-channel weights, MinMax calibration on unlabelled frames) of the
32 encoder convolutions (speed unchanged, +0.1-0.3 points of bad-3), and onnxruntime-openvino 1.24.1's OpenVINO
execution provider on the CPU (precision FP32 or ACCURACY, 2 threads; outputs within 0.001 px: 1.05-1.11x the CPU
provider's time on the AMX Xeon, 2026-11-26; its default precision there is bf16, which changes the output). The
convolutions already run near this CPU's float32 rate (110 GMAC per 376x1248 frame, ~0.9 s of the 1.3 s: ~240
GFLOP/s of the two cores' ~320-380 AVX-512 FMA peak), so a faster graph needs a smaller network, not a different
runtime.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import numpy.typing as npt
import torch
import torch.nn.functional as F
from torch import nn

from optstereo.checkpoint import CheckpointError, model_inference
from optstereo.choices import EXPORT_FORMATS as FORMATS
from optstereo.inference.cascade import grid_start
from optstereo.inference.config import InferenceConfig
from optstereo.inference.engine import check_refine, run
from pvm_labeler.common.atomic import atomic_path
from pvm_labeler.common.errors import ConfigError

logger = logging.getLogger(__name__)

OPSET = 18
#: The extra file of a TorchScript export that holds the model's InferenceConfig (JSON).
TORCHSCRIPT_CONFIG = "inference_config.json"


class InferenceGraph(nn.Module):
    """(left, right) -> full-resolution disparity of the last of ``iters`` GRU iterations (test mode); with a third
    input ``start`` (1, 1, H, W), a full-resolution disparity of the pair (zeros = the zero start), the GRU starts
    from it averaged onto the 1/8 grid (a model with ``InferenceConfig.coarse_start``, optstereo.inference.cascade)."""

    def __init__(self, model: nn.Module, iters: int | None = None) -> None:
        super().__init__()
        self.model = model
        self.iters = iters

    def forward(self, left: torch.Tensor, right: torch.Tensor, start: torch.Tensor | None = None) -> torch.Tensor:
        if start is None:
            return self.model(left, right, iters=self.iters, test_mode=True)[1]
        return self.model(left, right, iters=self.iters, test_mode=True, disp_init=grid_start(start))[1]


def export(model: nn.Module, out: Path, fmt: str = "onnx", iters: int | None = None,
           example_hw: tuple[int, int] = (64, 128), batch: bool = False) -> Path:
    """Write ``model``'s inference graph to ``out`` (.onnx or TorchScript .pt) and return the path.

    ``batch=False`` (default): batch size 1, per-image encoder/upsampler calls (faster); True: dynamic batch.
    """
    if fmt not in FORMATS:
        raise ValueError(f"export format must be one of {FORMATS}, got {fmt!r}")
    reason = getattr(model, "not_exportable", None)
    if reason:
        raise ConfigError(f"{type(model).__name__} cannot be exported: {reason}")
    model = model.cpu().eval()
    saved_chunk = getattr(model, "image_chunk", None)
    if hasattr(model, "image_chunk"):
        model.image_chunk = 0 if batch else 1  # the same outputs either way (tests/test_model_optstereo.py)
    config = model_inference(model)
    config = config if iters is None else config.replace(iters=iters)  # the graph's own, fixed here
    recorded = {"inference_config": json.dumps(config.to_dict())}
    cascade = config.coarse_start
    try:
        graph = InferenceGraph(model, config.iters).eval()  # the recorded iterations, not the model's default
        return _export(graph, Path(out), fmt, example_hw, batch, recorded, cascade)
    finally:
        if hasattr(model, "image_chunk"):
            model.image_chunk = saved_chunk


def _export(graph: nn.Module, out: Path, fmt: str, example_hw: tuple[int, int], batch: bool,
            recorded: dict[str, str], cascade: bool = False) -> Path:
    h, w = example_hw
    gen = torch.Generator().manual_seed(0)
    left = torch.rand(1, 3, h, w, generator=gen) * 255
    right = torch.roll(left, shifts=-2, dims=-1)
    inputs = (left, right, torch.full((left.shape[0], 1, h, w), 2.0)) if cascade else (left, right)
    names = ["left", "right", "start"][:len(inputs)]
    with atomic_path(out) as tmp, torch.no_grad():
        if fmt == "onnx":
            dims = {0: "batch", 2: "height", 3: "width"} if batch else {2: "height", 3: "width"}
            with _exporter_quiet():
                program = torch.onnx.export(graph, inputs, dynamo=True, input_names=names,
                                            output_names=["disparity"], dynamic_shapes={n: dims for n in names},
                                            opset_version=OPSET, optimize=False, verbose=False)
            # the model's InferenceConfig travels in the file: infer_onnx runs it, as infer does
            program.model.metadata_props.update(recorded)
            program.save(str(tmp), external_data=False)  # one self-contained file (weights ~10 MB, far below 2 GB)
        else:
            buffer = io.BytesIO()  # torch's file writer aborts the process on a full disk; Python's raises OSError
            # the InferenceConfig travels as an extra file: torch.jit.load(f, _extra_files={"inference_config.json":
            # ""}) reads it back (scale, iterations, the small-pair enlargement the graph itself does not do)
            torch.jit.save(torch.jit.trace(graph, inputs, check_trace=False), buffer,
                           _extra_files={TORCHSCRIPT_CONFIG: recorded["inference_config"]})
            tmp.write_bytes(buffer.getvalue())
    return out


@contextlib.contextmanager
def _exporter_quiet() -> Iterator[None]:
    """torch.onnx's exporter without its chatter, none of it about this model: warnings that torchvision's
    detection ops cannot be registered (not installed, not used), deprecations inside torch, onnx_ir's pass log and
    "axis name not used" for the height and width that the two images share. Errors still raise."""
    loggers = [logging.getLogger(name) for name in ("torch.onnx", "onnx_ir", "onnxscript")]
    levels = [lg.level for lg in loggers]
    try:
        for lg in loggers:
            lg.setLevel(logging.ERROR)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)
            warnings.filterwarnings("ignore", message=r".*axis name.*will not be used", category=UserWarning)
            yield
    finally:
        for lg, level in zip(loggers, levels, strict=True):
            lg.setLevel(level)


def onnx_session(path: Path | str, threads: int = 0):
    """An onnxruntime CPU session of an exported file (``threads`` 0 = onnxruntime's default), after
    :func:`check_external_data`."""
    import onnxruntime as ort  # lazy: onnxruntime is optional

    check_external_data(path)
    options = ort.SessionOptions()
    if threads:
        options.intra_op_num_threads = threads
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def check_external_data(path: Path | str) -> None:
    """Raise CheckpointError naming ``path`` unless it is an ONNX model whose tensors are in the file itself or in
    files inside its own folder (a relative location without ``..``).

    An ONNX file may keep tensors in other files, named by paths in it; the file is a user's input, so what it names
    is checked here rather than left to the installed onnxruntime (1.32 refuses such paths itself, with its own
    exception). ``optstereo-export`` writes self-contained files.
    """
    import onnx  # lazy: onnx is optional (the export extra, with onnxruntime)
    from google.protobuf.message import DecodeError  # lazy: protobuf comes with onnx

    path = Path(path)
    try:
        model = onnx.load_model(str(path), load_external_data=False)
    except (DecodeError, OSError, ValueError) as exc:
        raise CheckpointError(f"cannot read ONNX file {path}: {exc}") from exc
    for tensor in _tensors(model.graph, *(node for f in model.functions for node in f.node)):
        if tensor.data_location != onnx.TensorProto.EXTERNAL:
            continue
        location = next((entry.value for entry in tensor.external_data if entry.key == "location"), "")
        if not location or Path(location).is_absolute() or ".." in Path(location).parts:
            raise CheckpointError(f"ONNX file {path}: tensor {tensor.name!r} keeps its data in {location!r}, outside "
                                  f"the file's folder {path.parent}; refused (external data must sit beside the "
                                  f"file; optstereo-export writes self-contained files)")


def _tensors(graph, *nodes) -> Iterator:
    """Every TensorProto of an ONNX graph: initializers (sparse ones' values and indices) and the tensors in node
    attributes, subgraphs (If/Loop bodies) included, and in ``nodes`` (a model's functions)."""
    yield from graph.initializer
    for sparse in graph.sparse_initializer:
        yield from (sparse.values, sparse.indices)
    for node in (*graph.node, *nodes):
        for attr in node.attribute:
            yield from (attr.t, *attr.tensors)
            for sparse in (attr.sparse_tensor, *attr.sparse_tensors):
                yield from (sparse.values, sparse.indices)
            for sub in (attr.g, *attr.graphs):
                yield from _tensors(sub)


def infer_onnx(session, left: npt.NDArray[np.uint8], right: npt.NDArray[np.uint8],
               scale: float | None = None, refine: str | None = None) -> npt.NDArray[np.float32]:
    """(H, W, 3) uint8 pair -> (H, W) float32 disparity through an onnxruntime session, by
    ``optstereo.inference.engine.run``
    with the InferenceConfig the file records (:func:`onnx_inference_config`); ``scale``/``refine`` override it as
    ``infer``'s do (a given scale is final)."""
    if left.shape != right.shape:
        raise ValueError(f"left/right shapes differ: {left.shape} vs {right.shape}")
    config = onnx_inference_config(session)
    if scale is not None:
        config = config.fixed(scale)
    if refine is not None:
        check_refine(refine)
        config = config.replace(refine=refine)
    return run(OnnxNetwork(session), left, right, config).disparity


def onnx_inference_config(session) -> InferenceConfig:
    """The InferenceConfig an exported file records: its ``inference_config`` metadata, or in files written before
    it, the old per-key metadata (and ``coarse_start`` from the graph's third input)."""
    recorded = session.get_modelmeta().custom_metadata_map
    if "inference_config" in recorded:
        return InferenceConfig.from_dict(json.loads(recorded["inference_config"]))
    legacy: dict = {"scale": float(recorded.get("input_scale", 1.0)), "refine": recorded.get("refine", "none"),
                    "coarse_start": len(session.get_inputs()) == 3}
    if float(recorded.get("scale_ref_disp", 0.0)) > 0:
        legacy.update(adaptive_ref_disp=float(recorded["scale_ref_disp"]),
                      adaptive_ref_pixels=int(recorded["scale_ref_pixels"]))
    if recorded.get("cascade_select") == "1":
        legacy.update(select=True, select_jump=float(recorded.get("cascade_select_jump", 0.0)))
    return InferenceConfig.from_dict(legacy)


class OnnxNetwork(nn.Module):
    """An onnxruntime session with the model's forward contract, so that ``optstereo.inference.engine.run`` runs it as
    it
    runs the torch model: (left, right, iters, test_mode=True, disp_init) -> (None, (1, 1, H, W) disparity).

    ``iters`` is the graph's own (fixed at export). ``disp_init`` (1, 1, H/8, W/8) in 1/8-grid pixels reaches a
    graph with a ``start`` input as the full-resolution disparity whose 8x8 cell means it is (x8, each cell
    repeated), which the graph averages back onto the grid; a graph without one refuses it.
    """

    divisor = 8  # the exported OptStereo's multiple (optstereo.inference.padding.divisor_of)

    def __init__(self, session) -> None:
        super().__init__()
        self.session = session
        self.has_start = len(session.get_inputs()) == 3

    def forward(self, left: torch.Tensor, right: torch.Tensor, iters: int | None = None, test_mode: bool = True,
                disp_init: torch.Tensor | None = None) -> tuple[None, torch.Tensor]:
        feed = {"left": left.float().cpu().numpy(), "right": right.float().cpu().numpy()}
        if disp_init is not None and not self.has_start:
            raise ValueError("this ONNX graph has no start input: it was exported from a model without coarse_start")
        if self.has_start:
            start = torch.zeros(left.shape[0], 1, *left.shape[-2:]) if disp_init is None else \
                F.interpolate(disp_init.float().cpu(), scale_factor=8, mode="nearest") * 8
            feed["start"] = start.numpy()
        disp = self.session.run(["disparity"], feed)[0]
        return None, torch.from_numpy(disp).to(left.device)
