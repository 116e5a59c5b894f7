"""CPU inference engineering of OptStereo's test-mode pass: the same weights and function, less CPU time (issue 52).

``engineer(model)`` (called by ``optstereo.api.load_model`` and the CLIs' loader) returns an
:class:`EngineeredOptStereo` that shares the model's modules and parameters (the same state dict, nothing saved
changes). Its forward takes the path below for a float32 test-mode pass on the CPU without gradients, and
``OptStereo.forward`` for anything else (training, autograd, autocast, CUDA, ONNX/TorchScript export, torch.compile
tracing). The path computes the same function with fewer passes over memory:

- the features stay channels-last from the encoder to the GRU (the encoder went back to NCHW; the correlation's
  (B, H, W, C) view and every GRU convolution then copied layouts), and each residual block adds its shortcut in
  place;
- the cost-volume pyramid sits in one buffer, every level with a zero column on both sides, so the lookup is one
  gather of all levels and both taps with clamped indices (a clamped index lands on a zero column exactly where the
  plain lookup masks a tap outside the row) and no masks;
- the GRU's static part stays one tensor, its adds and activations run in place, and the lookup's (B, H, W, C)
  output enters the GRU as a channels-last view instead of a copy;
- the GRU's three per-iteration 3x3 convolutions (z and r, q, the head's first) run as Winograd F(4x4, 3x3)
  (``optstereo.inference.winograd``) on weights transformed once and cached (re-made when a weight changes), where
  that is faster on the machine: the first call of each convolution in a process times both ways on its real input
  (:data:`CALIBRATION_RUNS` each, alternating, the fastest run of each) and keeps the faster for the process
  (:func:`winograd_choices`). Winograd won on an Intel Xeon (AVX-512) and an AVX2 EPYC, direct convolutions on a
  Zen 5 EPYC (``make bench``, section ``models``);
- the encoder's convolutions after the stem run in int8 (:mod:`optstereo.inference.int8`) where the weights file
  has int8 clips and the CPU runs oneDNN's int8 convolution at AVX2 or AVX-512 (:func:`int8_encoder`): not the same
  function (~0.04 px mean from float32; registration Q1), off with ``OPTSTEREO_INT8=0``;
- glibc keeps freed large buffers (:func:`keep_freed_buffers`) so that activations reuse mapped memory.

In float32 the outputs equal the plain path's to float32 rounding (oneDNN picks other kernels for channels-last
convolutions):
tests/test_fastpath.py holds them together on a tiny random model and on a real KITTI pair with the shipped weights.
Measured in ``make bench`` (section ``models``); the steps tried and their ratios are in docs/optstereo.md.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import math
import os
import sys
import time
from collections.abc import Callable, Iterator
from typing import Literal, NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from optstereo.inference import int8
from optstereo.inference.winograd import winograd_conv3x3, winograd_weight
from optstereo.models.correlation import CorrBlock1D
from optstereo.models.extractor import FeatureEncoder
from optstereo.models.layers import ResidualBlock, SeparableBlock
from optstereo.models.optstereo import OptStereo, normalize_image, resolve_iters
from optstereo.models.update import ConvGRU, DispHead

CHANNELS_LAST = torch.channels_last
WinogradMode = bool | Literal["auto"]
#: Set by :func:`engineering`; int8's default from ``OPTSTEREO_INT8`` ("0": the float32 encoder everywhere).
_switches: dict[str, bool | str] = {"enabled": True, "winograd": "auto",
                                    "int8": os.environ.get("OPTSTEREO_INT8", "1") != "0"}
Conv = Callable[[torch.Tensor], torch.Tensor]
#: Timed runs of each way on the first call of a loop convolution (the fastest of each counts; the first run of each
#: also pays oneDNN's primitive set-up, so at least two).
CALIBRATION_RUNS = 3
#: Per (role, weight shape, threads): True when Winograd was the faster in this process (:func:`winograd_choices`).
_choices: dict[tuple[str, tuple[int, ...], int], bool] = {}
_clock: Callable[[], float] = time.perf_counter  # replaced in tests


@contextlib.contextmanager
def engineering(enabled: bool, *, winograd: WinogradMode = "auto", int8: bool | None = None) -> Iterator[None]:
    """Turn the engineered path on or off inside the block (plain ``OptStereo.forward`` when off), and choose its GRU
    convolutions: Winograd (True), direct (False) or the faster on this machine ("auto", the default), e.g. to time
    them in one process; ``int8=False`` keeps the encoder float32 where it would run in int8
    (:func:`int8_encoder`), True allows it, None leaves the setting as it is (``OPTSTEREO_INT8``)."""
    old = dict(_switches)
    _switches.update(enabled=enabled, winograd=winograd, int8=_switches["int8"] if int8 is None else int8)
    try:
        yield
    finally:
        _switches.update(old)


class LoopConvs(NamedTuple):
    """The GRU loop's per-iteration 3x3 convolutions: W_zr, W_q (on [h, x] and [r * h, x]) and the head's first."""

    zr: Conv
    q: Conv
    head: Conv


def engineer(model: nn.Module) -> nn.Module:
    """``model`` prepared for CPU inference: an :class:`EngineeredOptStereo` sharing its modules and parameters when
    it is an OptStereo with the standard parts (encoder, 1-D correlation, GRU with a static part, disparity head),
    else ``model`` itself. Also keeps the process's large freed buffers for reuse (:func:`keep_freed_buffers`)."""
    if type(model) is not OptStereo or not supported(model):
        return model
    keep_freed_buffers()
    return EngineeredOptStereo.from_model(model)


#: glibc's ``mallopt`` parameters and the values :func:`keep_freed_buffers` sets.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
MMAP_THRESHOLD = 32 << 20  # glibc's largest (64-bit): a buffer below it comes from the heap
TRIM_THRESHOLD = 1 << 30  # free heap kept before memory goes back to the system
_heap_state: dict[str, bool] = {}


def keep_freed_buffers() -> bool:
    """Once per process, on glibc: allocate buffers below 32 MiB from the heap and keep up to 1 GiB of freed heap
    (``mallopt``), so that a pass's large activations (30 MB per 64-channel map of a KITTI frame at 1/2 resolution)
    reuse memory already mapped instead of faulting fresh pages in each time (~10 ms per such map on a Zen 5 EPYC,
    a third of an int8 convolution's time). glibc's default moves both limits as blocks are freed, so whether a map
    faults depended on what the pass freed before it. The cost: the process keeps up to 1 GiB it freed.
    ``OPTSTEREO_KEEP_HEAP=0`` leaves malloc alone. Returns whether the settings were made (False elsewhere)."""
    if "done" in _heap_state:
        return _heap_state["done"]
    done = False
    if os.environ.get("OPTSTEREO_KEEP_HEAP", "1") != "0" and sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL("libc.so.6")
            done = bool(libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
                libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
        except (OSError, AttributeError):  # not glibc (musl has no mallopt)
            done = False
    _heap_state["done"] = done
    return done


def supported(model: OptStereo) -> bool:
    """Whether the engineered path knows every part of ``model`` (the upsampler is called as it is)."""
    encoder = model.feature_encoder
    return (type(encoder) is FeatureEncoder and type(model.corr_block) is CorrBlock1D
            and type(model.update_block) is ConvGRU and model.update_block.static is not None
            and type(model.disp_head) is DispHead
            and all(type(block) in (ResidualBlock, SeparableBlock) for layer in (encoder.layer1, encoder.layer2)
                    for block in layer)
            and all(type(block) is ResidualBlock for block in encoder.layer3))


class EngineeredOptStereo(OptStereo):
    """OptStereo whose CPU float32 test-mode pass without gradients runs :func:`engineered_pass` (module doc)."""

    @classmethod
    def from_model(cls, model: OptStereo) -> EngineeredOptStereo:
        """A view of ``model``: the same module objects (so the same parameters and state dict), its mode and its
        ``inference_config``."""
        new = cls(feature_encoder=model.feature_encoder, corr_block=model.corr_block, hidden_init=model.hidden_init,
                  update_block=model.update_block, disp_head=model.disp_head, upsampler=model.upsampler,
                  iters=model.iters, config=model.config, image_chunk=model.image_chunk)
        if hasattr(model, "inference_config"):
            new.inference_config = model.inference_config
        new.int8_calibration = getattr(model, "int8_calibration", None)
        return new.train(model.training)

    def forward(self, left: torch.Tensor, right: torch.Tensor, iters: int | None = None, test_mode: bool = False,
                disp_init: torch.Tensor | None = None) -> list[torch.Tensor] | tuple[torch.Tensor, torch.Tensor]:
        if test_mode and _fast_path_applies(left):
            return engineered_pass(self, left, right, iters, disp_init, self.loop_convs(left.shape[0]))
        return super().forward(left, right, iters=iters, test_mode=test_mode, disp_init=disp_init)

    def loop_convs(self, batch: int) -> LoopConvs:
        """The loop's convolutions for one image: Winograd versions, the modules themselves (direct), or with the
        switch at "auto" whichever of the two this machine runs faster (:func:`faster_of`); direct for a batch."""
        convs = LoopConvs(self.update_block.convzr, self.update_block.convq, self.disp_head.conv1)
        mode = _switches["winograd"]
        if batch != 1 or mode is False:
            return convs
        pairs = zip(LoopConvs._fields, convs, strict=True)
        if mode is True:
            return LoopConvs(*(self._winograd(role, conv) for role, conv in pairs))
        return LoopConvs(*(faster_of(role, conv, lambda r=role, c=conv: self._winograd(r, c)) for role, conv in pairs))

    def _winograd(self, role: str, conv: nn.Conv2d) -> Conv:
        """``conv`` as a Winograd convolution; its transformed weight cached until the weight changes (another
        parameter, or the same one changed in place: an optimiser step or ``load_state_dict`` bumps its version).
        A weight made under ``torch.inference_mode`` (a model loaded there) has no version: transformed anew."""
        if conv.weight.is_inference():
            u = winograd_weight(conv.weight)
            return lambda x: winograd_conv3x3(x, u, conv.bias)
        cache: dict[str, tuple[torch.Tensor, int, torch.Tensor]] = self.__dict__.setdefault("_winograd_cache", {})
        hit = cache.get(role)
        if hit is None or hit[0] is not conv.weight or hit[1] != conv.weight._version:
            hit = cache[role] = (conv.weight, conv.weight._version, winograd_weight(conv.weight))
        u, bias = hit[2], conv.bias
        return lambda x: winograd_conv3x3(x, u, bias)


def faster_of(role: str, direct: nn.Conv2d, make_winograd: Callable[[], Conv]) -> Conv:
    """The Winograd convolution (made by ``make_winograd`` only when it is used: a weight loaded under inference mode
    is transformed anew each time) or ``direct``, whichever was the faster in this process for this role, weight
    shape and thread count; not yet known: the first call times both on its input (:data:`CALIBRATION_RUNS`
    alternating runs each, the fastest of each) and records the choice. Both compute the same convolution (to
    float32 rounding)."""
    key = (role, tuple(direct.weight.shape), torch.get_num_threads())
    known = _choices.get(key)
    if known is not None:
        return make_winograd() if known else direct
    winograd = make_winograd()

    def calibrate(x: torch.Tensor) -> torch.Tensor:
        if key in _choices:  # the later iterations of the pass that calibrated
            return (winograd if _choices[key] else direct)(x)
        best = {True: math.inf, False: math.inf}
        for _ in range(CALIBRATION_RUNS):
            for way, conv in ((True, winograd), (False, direct)):
                start = _clock()
                out = conv(x)
                best[way] = min(best[way], _clock() - start)
        _choices[key] = best[True] < best[False]
        return out

    return calibrate


def winograd_choices() -> dict[str, bool]:
    """The choices made in this process: "<role> <weight shape> <threads> threads" -> True (Winograd) / False."""
    return {f"{role} {'x'.join(map(str, shape))} {threads} threads": way
            for (role, shape, threads), way in _choices.items()}


def _fast_path_applies(left: torch.Tensor) -> bool:
    """Float32 CPU inference in eager mode: no autograd, no autocast, no export or tracing."""
    return (_switches["enabled"] and left.device.type == "cpu" and left.dtype == torch.float32
            and not torch.is_grad_enabled() and not torch.is_autocast_enabled("cpu") and not torch.jit.is_tracing()
            and not torch.onnx.is_in_onnx_export() and not torch.compiler.is_compiling())


def engineered_pass(model: OptStereo, left: torch.Tensor, right: torch.Tensor, iters: int | None = None,
                    disp_init: torch.Tensor | None = None,
                    convs: LoopConvs | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """``model(left, right, iters, test_mode=True, disp_init)`` computed as the module doc says: (D_s (B, 1, H/8,
    W/8), D (B, 1, H, W)). ``convs``: the loop's convolutions (None = the model's modules)."""
    gru, head = model.update_block, model.disp_head
    convs = convs or LoopConvs(gru.convzr, gru.convq, head.conv1)
    model._check_inputs(left, right)
    iters = resolve_iters(iters, model.iters)
    image_left = normalize_image(left)
    images = torch.cat([image_left, normalize_image(right)], dim=0)
    chunk = model._chunk_size(images) if model._per_image_encoder else 0
    encoder = int8_encoder(model) or functools.partial(encode, model.feature_encoder)
    feats = model._in_chunks(encoder, chunk, images)
    feat_left, feat_right = feats.chunk(2, dim=0)
    corr = model.corr_block
    volume, level_widths = padded_pyramid(feat_left, feat_right, corr.num_levels, corr.scale)
    taps = lookup_taps(level_widths, corr.radius, left.device)
    start = int8_gru_init(model)
    if start is None:
        hidden = model.hidden_init(feat_left)
        static = gru.static(feat_left)  # (B, 3 * hidden) = [z | r | q], channels-last
    else:
        static, hidden = start(feat_left)
    b, _, h8, w8 = feat_left.shape
    disp = torch.zeros(b, 1, h8, w8, device=left.device, dtype=torch.float32)
    if disp_init is not None:
        if tuple(disp_init.shape) != (b, 1, h8, w8):
            raise ValueError(f"disp_init must be (B, 1, H/8, W/8) = {(b, 1, h8, w8)}, got {tuple(disp_init.shape)}")
        disp = disp_init.float().to(left.device)
    for _ in range(iters):
        sampled = lookup(volume, taps, disp)  # (B, H, W, L * (2d + 1))
        x = torch.cat([disp.permute(0, 2, 3, 1), sampled], dim=3).permute(0, 3, 1, 2)  # [D, M_l], channels-last
        hidden = gru_step(gru, convs, hidden, x, static)
        disp = disp + head.conv2(head.relu(convs.head(hidden)))  # DispHead
    return disp, model._upsample(disp, hidden, image_left)


def _int8_calibration(model: OptStereo) -> int8.Int8Calibration | None:
    """The model's int8 clips when int8 may run: the weights file has them (``model.int8_calibration``), this CPU runs
    them fast (:func:`int8.available`) and the switch allows it (:func:`engineering`); else None."""
    calibration = getattr(model, "int8_calibration", None)
    return calibration if calibration is not None and _switches["int8"] and int8.available() else None


def int8_encoder(model: OptStereo) -> int8.Int8Encoder | None:
    """The model's encoder with int8 convolutions (:mod:`optstereo.inference.int8`, registration Q1) when int8 may
    run (:func:`_int8_calibration`) and the encoder is one it knows; else None (the float32 :func:`encode`). Built
    once per model, rebuilt when an encoder weight or the clips change."""
    calibration = _int8_calibration(model)
    if calibration is None or not int8.supported(model.feature_encoder):
        return None
    built = model.__dict__.get("_int8_encoder")
    if (built is None or built.encoder is not model.feature_encoder or built.calibration is not calibration
            or not built.current()):
        built = model.__dict__["_int8_encoder"] = int8.Int8Encoder(model.feature_encoder, calibration)
    return built


def int8_gru_init(model: OptStereo) -> int8.Int8GruInit | None:
    """The GRU's static and ``hidden_init`` convolutions as one int8 convolution (registration Q3, on top of Q1's
    encoder) when int8 may run, the encoder is one :class:`int8.Int8Encoder` knows and the clips have F_l's range
    (``gru_init``); else None (float32). Built once per model, rebuilt when one of their weights or the clips
    change."""
    calibration = _int8_calibration(model)
    if (calibration is None or "gru_init" not in calibration.ranges or not int8.supported(model.feature_encoder)
            or not int8.supported_gru_init(model)):
        return None
    built = model.__dict__.get("_int8_gru_init")
    if built is None or built.calibration is not calibration or not built.current():
        built = model.__dict__["_int8_gru_init"] = int8.Int8GruInit(model.update_block.static, model.hidden_init.conv,
                                                                    calibration)
    return built


def encode(encoder: FeatureEncoder, x: torch.Tensor) -> torch.Tensor:
    """``FeatureEncoder`` on (B, 3, H, W) -> (B, C, H/8, W/8), channels-last throughout, shortcuts added in place."""
    x = encoder.stem(x.contiguous(memory_format=CHANNELS_LAST))
    for layer in (encoder.layer1, encoder.layer2, encoder.layer3):
        for block in layer:
            if type(block) is SeparableBlock:  # relu(shortcut(x) + pw2(dw2(relu(pw1(dw1(x)))))), adds in place
                y = block.pw2(block.dw2(block.pw1(block.dw1(x)).relu_()))
                x = y.add_(block.shortcut(x)).relu_()
                continue
            if type(block) is not ResidualBlock:  # a block this path does not know runs as it is
                x = block(x)
                continue
            y = block.relu(block.norm1(block.conv1(x)))
            y = block.relu(block.norm2(block.conv2(y)))
            x = y.add_(block.shortcut(x)).relu_()  # relu(shortcut(x) + y): the same sum, no new tensor
    return encoder.proj(x)


def padded_pyramid(feat_left: torch.Tensor, feat_right: torch.Tensor, num_levels: int,
                   scale: bool) -> tuple[torch.Tensor, list[int]]:
    """The correlation pyramid of ``optstereo.models.correlation`` in one (B, H, W, sum_k (W_k + 2)) float32 buffer:
    level k's W_k entries between two zero columns, levels side by side. Returns the buffer and [W_0, ..., W_{L-1}].
    """
    b, c, h, w = feat_left.shape
    fl = feat_left.float().permute(0, 2, 3, 1)  # (B, H, W, C): a view of channels-last features
    fr = feat_right.float().permute(0, 2, 1, 3)  # (B, H, C, W)
    level = torch.matmul(fl, fr)
    if scale:
        level.div_(math.sqrt(c))
    widths = [w]
    for _ in range(num_levels - 1):
        widths.append(widths[-1] // 2)
    volume = level.new_zeros(b, h, w, sum(wk + 2 for wk in widths))
    start = 1
    for k, wk in enumerate(widths):
        if k:  # M_k = avg_pool(M_{k-1}) along the last dimension, as build_pyramid
            level = F.avg_pool1d(level.reshape(b * h * w, 1, level.shape[-1]), kernel_size=2, stride=2)
            level = level.reshape(b, h, w, wk)
        volume[..., start:start + wk] = level
        start += wk + 2
    return volume, widths


def lookup_taps(widths: list[int], radius: int, device: torch.device) -> tuple[torch.Tensor, ...]:
    """Per output channel k * (2d + 1) + (dj + d) of the lookup: (dj, 1 / 2^k, W_k, offset of level k's first entry
    in the padded buffer), each (L * (2d + 1),) float32."""
    n = 2 * radius + 1
    starts, start = [], 1
    for wk in widths:
        starts.append(start)
        start += wk + 2

    def per_level(values: list[float]) -> torch.Tensor:
        return torch.tensor(values, dtype=torch.float32, device=device).repeat_interleave(n)

    offsets = torch.arange(-radius, radius + 1, dtype=torch.float32, device=device).repeat(len(widths))
    return (offsets, per_level([0.5 ** k for k in range(len(widths))]), per_level([float(wk) for wk in widths]),
            per_level([float(s) for s in starts]))


def lookup(volume: torch.Tensor, taps: tuple[torch.Tensor, ...], disp: torch.Tensor) -> torch.Tensor:
    """``optstereo.models.correlation.lookup_pyramid`` on the padded buffer: (B, 1, H, W) disparity -> (B, H, W,
    L * (2d + 1)) float32 (the same values; the caller's permute gives the (B, C, H, W) channels-last view).

    Positions j'/2^k + dj are the plain lookup's (times an exact power of two); a tap index clamped to [-1, W_k]
    reads one of the level's zero columns exactly when the plain lookup masks it to zero.
    """
    offsets, inv_scale, width, start = taps
    w = disp.shape[-1]
    cols = torch.arange(w, device=disp.device, dtype=torch.float32).view(1, 1, w)
    target = (cols - disp[:, 0].float()).unsqueeze(-1)  # (B, H, W, 1): j' = j - D
    pos = target * inv_scale + offsets  # (B, H, W, L * (2d + 1))
    x0 = torch.floor(pos)
    frac = pos - x0
    lowest = torch.full_like(width, -1.0)
    index = torch.cat([torch.clamp(x0, lowest, width).add_(start), torch.clamp(x0 + 1, lowest, width).add_(start)],
                      dim=3).long()
    values = torch.gather(volume, 3, index)
    n = pos.shape[-1]
    return values[..., :n] * (1.0 - frac) + values[..., n:] * frac


def gru_step(gru: ConvGRU, convs: LoopConvs, hidden: torch.Tensor, x: torch.Tensor,
             static: torch.Tensor) -> torch.Tensor:
    """``ConvGRU.forward(hidden, x, precompute(F_l))`` with the static part as one (B, 3 * hidden) tensor, the adds
    and activations in place (the same arithmetic), the convolutions ``convs.zr`` and ``convs.q``."""
    n = gru.hidden_dim
    zr = convs.zr(torch.cat([hidden, x], dim=1)).add_(static[:, :2 * n]).sigmoid_()
    z, r = zr.chunk(2, dim=1)
    q = convs.q(torch.cat([r * hidden, x], dim=1)).add_(static[:, 2 * n:]).tanh_()
    return (1 - z).mul_(hidden).add_(q.mul_(z))  # (1 - z) * h + z * q
