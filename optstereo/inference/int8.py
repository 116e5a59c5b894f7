"""The encoder's convolutions in int8 on x86 CPUs (issue 52, registration Q1 in docs/registrations.md).

Most of a CPU pass of the default model is its encoder's 3x3 convolutions at 1/2, 1/4 and 1/8 resolution (64, 96 and
128 channels). oneDNN runs them on uint8 activations and int8 weights with int32 sums: about half the time of
float32 on an AVX2 CPU, a quarter with AVX-512 VNNI. This module runs the 15 convolutions after the stem (layers 1-3
and the 1x1 projection) that way, with float32 outputs (:class:`Int8Encoder`, registration Q1), and the GRU's two
start convolutions on F_l as one (:class:`Int8GruInit`, Q3); the stem, the instance norms, the correlation, the GRU
loop and the upsampler stay float32.

- Weights: symmetric, one scale per output channel (``max |w| / 127``), quantised once when the model is loaded.
- Activations: uint8, one scale per tensor, from a fixed **clip** per convolution (its input value mapped to 255):
  every input of these convolutions follows a ReLU (>= 0, zero point 0), and instance norm keeps their range nearly
  the same from image to image, so clips measured once on unlabelled pairs
  (:func:`optstereo.inference.int8_calibration.calibrate`, the mean 99.999th percentile) hold; a value above its
  clip saturates.
- Fewer passes over memory: the instance norm before a block's second convolution writes its input already scaled
  (its affine weight ``1 / scale``, bias 0.5: one clamp and a cast make the uint8 tensor), a block's first
  convolution and its strided shortcut share one quantised input, and the ReLU after an identity shortcut's sum (of
  two non-negative tensors) is skipped.

The clips of a weights file live beside it, in ``<file>.int8.json`` (:func:`sidecar_path`), with the file's SHA-256:
``optstereo.checkpoint.build_model_from_checkpoint`` attaches them to the model (``model.int8_calibration``) and
:mod:`optstereo.inference.fastpath` encodes with them when :func:`available` (an x86 CPU torch runs at AVX2 or
AVX-512, with oneDNN's int8 convolution) and the switch allows (``fastpath.engineering(int8=False)`` turns it off).
The outputs are not float32's: on validation pairs they moved by ~0.04 px mean; Q1's accuracy rule and its scores are
in docs/registrations.md and RESULTS.md.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn

from optstereo.models.extractor import FeatureEncoder
from optstereo.models.layers import InstanceNorm2d, ResidualBlock

#: The quantile of each convolution's input that maps to 255 (chosen by output equality on validation pairs).
CLIP_QUANTILE = 0.99999
SIDECAR_SUFFIX = ".int8.json"
FORMAT = "optstereo-int8-clips/1"
_HALF = 0.5


@dataclass(frozen=True)
class Int8Calibration:
    """Per-convolution input clips of one weights file.

    Attributes:
        clips: encoder module name (``layer1.0.conv1``, ..., ``proj``) -> the input value mapped to uint8 255 (> 0).
        weights_sha256: SHA-256 of the weights file the clips were measured with.
        quantile: the quantile of each input the clip is (the mean over the calibration pairs).
        pairs: how many pairs were measured.
        ranges: signed inputs: name -> (low, high), the values mapped to uint8 0 and 255 (``gru_init``: F_l, the
            input of the GRU's static convolution and of ``hidden_init``; registration Q3). Optional.
    """

    clips: dict[str, float]
    weights_sha256: str
    quantile: float = CLIP_QUANTILE
    pairs: int = 0
    ranges: dict[str, tuple[float, float]] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"format": FORMAT, "weights_sha256": self.weights_sha256, "quantile": self.quantile,
                "pairs": self.pairs, "clips": dict(sorted(self.clips.items())),
                "ranges": {k: list(v) for k, v in sorted(self.ranges.items())}}

    @classmethod
    def from_dict(cls, values: dict[str, Any], source: Path | str = "<dict>") -> Int8Calibration:
        """Raises ValueError naming ``source`` and the problem for a file of another format or a bad clip."""
        if values.get("format") != FORMAT:
            raise ValueError(f"{source}: not an int8 clip file (format {values.get('format')!r}, expected {FORMAT!r})")
        clips = values.get("clips")
        if not isinstance(clips, dict) or not clips:
            raise ValueError(f"{source}: 'clips' must be a non-empty mapping of encoder convolutions to clips")
        for name, clip in clips.items():
            if isinstance(clip, bool) or not isinstance(clip, (int, float)) or not math.isfinite(clip) or clip <= 0:
                raise ValueError(f"{source}: clip of {name!r} must be a positive finite number, got {clip!r}")
        ranges = values.get("ranges", {})
        for name, pair in ranges.items():
            if (not isinstance(pair, list) or len(pair) != 2 or not all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in pair)
                    or not pair[0] < 0 < pair[1]):
                raise ValueError(f"{source}: range of {name!r} must be [low < 0, high > 0], got {pair!r}")
        return cls(clips={k: float(v) for k, v in clips.items()}, weights_sha256=str(values.get("weights_sha256", "")),
                   quantile=float(values.get("quantile", CLIP_QUANTILE)), pairs=int(values.get("pairs", 0)),
                   ranges={k: (float(v[0]), float(v[1])) for k, v in ranges.items()})


def sidecar_path(weights: Path) -> Path:
    """``<weights file>.int8.json``: where a weights file's clips live."""
    return Path(str(weights) + SIDECAR_SUFFIX)


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def read_sidecar(weights: Path) -> Int8Calibration | None:
    """The clips beside ``weights`` (None when there is no sidecar). A sidecar measured with other weights (its
    SHA-256 differs) is ignored with a warning naming both files: the float32 pass runs. An unreadable one raises
    ValueError naming it."""
    path = sidecar_path(Path(weights))
    if not path.is_file():
        return None
    try:
        values = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: unreadable int8 clip file ({exc})") from exc
    calibration = Int8Calibration.from_dict(values, path)
    if calibration.weights_sha256 != file_sha256(Path(weights)):
        warnings.warn(f"{path} was measured with other weights than {weights}: int8 is off for them (measure them "
                      f"again: `python -m optstereo.inference.int8_calibration`)", stacklevel=2)
        return None
    return calibration


def write_sidecar(weights: Path, calibration: Int8Calibration) -> Path:
    """Write ``calibration`` beside ``weights`` (atomically: a temporary file renamed) and return its path."""
    path = sidecar_path(Path(weights))
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(json.dumps(calibration.to_dict(), indent=1) + "\n")
    tmp.replace(path)
    return path


@functools.cache
def available() -> bool:
    """Whether this process can run the int8 convolutions fast: oneDNN's int8 convolution is in torch and torch runs
    at AVX2 or AVX-512 (older x86 CPUs and other architectures would take slow reference kernels or none). Asked
    once per process (torch fixes its CPU capability at start-up); every pass asks it."""
    return (hasattr(torch.ops.onednn, "qconv2d_pointwise") and hasattr(torch.ops.onednn, "qconv_prepack")
            and torch.backends.mkldnn.is_available()
            and torch.backends.cpu.get_cpu_capability() in ("AVX2", "AVX512"))


def conv_names(encoder: nn.Module) -> list[str]:
    """The encoder's convolutions this module runs in int8: every ``nn.Conv2d`` after the stem."""
    return [name for name, module in encoder.named_modules()
            if isinstance(module, nn.Conv2d) and not name.startswith("stem")]


class Int8Conv:
    """One ``nn.Conv2d`` with int8 weights on a uint8 input of a fixed scale and zero point: (B, C_in, H, W) uint8
    channels-last -> (B, C_out, H', W') float32 channels-last, ``conv(scale * (q - zero))`` to int8 rounding. The
    input range is [``low``, ``clip``] (``low`` 0: a ReLU's output, zero point 0)."""

    def __init__(self, conv: nn.Conv2d, clip: float, low: float = 0.0) -> None:
        weight = conv.weight.detach().float().cpu()
        self.scale = (float(clip) - float(low)) / 255.0
        self.zero = int(round(-float(low) / self.scale))
        self.w_scale = (weight.abs().amax(dim=(1, 2, 3)).clamp_min(1e-12) / 127.0).contiguous()
        q_weight = torch.round(weight / self.w_scale[:, None, None, None]).clamp_(-127, 127).to(torch.int8)
        self.stride, self.padding = list(conv.stride), list(conv.padding)
        self.dilation, self.groups = list(conv.dilation), conv.groups
        self.packed = torch.ops.onednn.qconv_prepack(q_weight, self.w_scale, self.scale, self.zero, self.stride,
                                                     self.padding, self.dilation, self.groups, None)
        self.w_zero = torch.zeros(weight.shape[0], dtype=torch.int32)
        self.bias = None if conv.bias is None else conv.bias.detach().float().cpu()

    def __call__(self, q: torch.Tensor) -> torch.Tensor:
        return torch.ops.onednn.qconv2d_pointwise(q, self.scale, self.zero, self.packed, self.w_scale, self.w_zero,
                                                  self.bias, self.stride, self.padding, self.dilation, self.groups,
                                                  1.0, 0, torch.float32, "none", [], "")

    def quantize(self, x: torch.Tensor) -> torch.Tensor:
        """Float32 ``x`` -> this convolution's uint8 input (:func:`quantize` at its scale and zero point)."""
        return quantize(x, self.scale, self.zero)


#: Largest float32 temporary the passes below allocate: glibc maps a block over its largest mmap threshold (32 MiB)
#: afresh, page faults and all, on every call, and the first encoder stage of a pair over ~524,000 pixels makes such
#: tensors (registration T9). So they work in place, or in bands of rows under this size.
BAND_BYTES = 16 << 20


def row_bands(x: torch.Tensor) -> list[slice]:
    """Slices of dim 2 (rows) of a (B, C, H, W) tensor whose bands (all B images, at ``x``'s element size) stay under
    :data:`BAND_BYTES` (one slice for a small tensor)."""
    row_bytes = x.element_size() * x.numel() // max(1, x.shape[2])
    step = max(1, BAND_BYTES // max(1, row_bytes))
    return [slice(start, start + step) for start in range(0, x.shape[2], step)]


def quantize(x: torch.Tensor, scale: float, zero: int = 0) -> torch.Tensor:
    """Float32 ``x`` -> uint8 ``round(x / scale) + zero`` saturated to [0, 255] (same shape and memory format),
    computed band by band (:func:`row_bands`) so no full-size float32 temporary is made; ``x`` is left as it is."""
    out = torch.empty_like(x, dtype=torch.uint8)
    offset = torch.tensor(zero + _HALF)
    for rows in row_bands(x):
        out[:, :, rows].copy_(torch.add(offset, x[:, :, rows], alpha=1.0 / scale).clamp_(0.0, 255.0))
    return out


def _instance_affine_(y: torch.Tensor, eps: float, weight: float | None = None, bias: float = 0.0) -> torch.Tensor:
    """``instance_norm(y) * weight + bias`` of one image (B = 1), written into ``y`` itself by batch norm's own
    kernel (training-mode statistics, the output aliased to the input: the same values as ``F.batch_norm``, no
    second full-size tensor)."""
    channels = y.shape[1]
    w = None if weight is None else torch.full((channels,), weight)
    b = None if weight is None else torch.full((channels,), bias)
    stats = torch.empty(channels), torch.empty(channels)
    torch.ops.aten.native_batch_norm.out(y, w, b, None, None, True, 0.0, eps, out=y, save_mean=stats[0],
                                         save_invstd=stats[1])
    return y


def norm_relu_quantize(y: torch.Tensor, eps: float, scale: float) -> torch.Tensor:
    """``quantize(relu(instance_norm(y)), scale)`` for one image (B = 1), overwriting ``y`` (a convolution's output):
    the norm writes ``IN(y) / scale + 0.5`` in place, a clamp to [0, 255] is the ReLU and the saturation, the cast
    rounds."""
    return _instance_affine_(y, eps, 1.0 / scale, _HALF).clamp_(0.0, 255.0).to(torch.uint8)


def _norm_relu(y: torch.Tensor, eps: float) -> torch.Tensor:
    """``relu(instance_norm(y))`` of one image, in place."""
    return _instance_affine_(y, eps).relu_()


class Int8Encoder:
    """A ``FeatureEncoder`` (residual stages) with :class:`Int8Conv` after its stem: (B, 3, H, W) normalised image ->
    (B, C, H/8, W/8) float32 channels-last features. Built once per model; rebuilt when a weight changes
    (:meth:`current`)."""

    def __init__(self, encoder: nn.Module, calibration: Int8Calibration) -> None:
        names = conv_names(encoder)
        missing = [n for n in names if n not in calibration.clips]
        if missing:
            raise ValueError(f"int8 clips are missing for {missing[:3]} ({len(missing)} of {len(names)} convolutions)")
        modules = dict(encoder.named_modules())
        self.encoder = encoder
        self.calibration = calibration
        self.convs: dict[str, Int8Conv] = {}
        for name in names:
            clip = calibration.clips[name]
            if name.endswith("shortcut.0"):  # the same input as the block's conv1: one quantised tensor for both
                clip = calibration.clips[name[:-len("shortcut.0")] + "conv1"]
            self.convs[name] = Int8Conv(modules[name], clip)
        self._versions = _versions(list(encoder.parameters()))

    def current(self) -> bool:
        """False when a parameter of the encoder changed since the weights were quantised (an optimiser step, a
        ``load_state_dict``)."""
        return _versions(list(self.encoder.parameters())) == self._versions

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[0] != 1:  # instance norm as batch norm needs one image per call
            return torch.cat([self(image) for image in x.split(1)], dim=0)
        encoder = self.encoder
        stem = encoder.stem  # conv, instance norm, ReLU: the norm and the ReLU in place on the conv's output
        x = _norm_relu(stem[0](x.contiguous(memory_format=torch.channels_last)), stem[1].eps)
        for index, layer in enumerate((encoder.layer1, encoder.layer2, encoder.layer3), start=1):
            for block_index, block in enumerate(layer):
                x = self._block(block, f"layer{index}.{block_index}.", x)
        return self.convs["proj"](self.convs["proj"].quantize(x))

    def _block(self, block: nn.Module, prefix: str, x: torch.Tensor) -> torch.Tensor:
        conv1, conv2 = self.convs[prefix + "conv1"], self.convs[prefix + "conv2"]
        qx = conv1.quantize(x)
        y = norm_relu_quantize(conv1(qx), block.norm1.eps, conv2.scale)
        y = _norm_relu(conv2(y), block.norm2.eps)
        if isinstance(block.shortcut, nn.Identity):
            return y.add_(x)  # both >= 0: the block's final ReLU changes nothing
        shortcut = block.shortcut[1](self.convs[prefix + "shortcut.0"](qx))
        return y.add_(shortcut).relu_()


class Int8GruInit:
    """The GRU's static convolution and ``hidden_init``'s, both on F_l, as one int8 convolution (registration Q3):
    (B, C, H/8, W/8) float32 F_l -> (static (B, 3 * hidden), h^0 = tanh(...) (B, hidden)), channels-last. F_l is
    signed: uint8 with a zero point over the calibrated ``gru_init`` range."""

    def __init__(self, static: nn.Conv2d, hidden: nn.Conv2d, calibration: Int8Calibration) -> None:
        low, high = calibration.ranges["gru_init"]
        self.calibration = calibration
        joint = nn.Conv2d(static.in_channels, static.out_channels + hidden.out_channels, static.kernel_size,
                          padding=static.padding, bias=True)
        with torch.no_grad():
            joint.weight.copy_(torch.cat([static.weight.detach().cpu(), hidden.weight.detach().cpu()]))
            static_bias = (torch.zeros(static.out_channels) if static.bias is None else static.bias.detach().cpu())
            hidden_bias = torch.zeros(hidden.out_channels) if hidden.bias is None else hidden.bias.detach().cpu()
            joint.bias.copy_(torch.cat([static_bias, hidden_bias]))
        self.conv = Int8Conv(joint, high, low)
        self.split = static.out_channels
        self.params = [static.weight, hidden.weight, *(() if hidden.bias is None else (hidden.bias,))]
        self._versions = _versions(self.params)

    def current(self) -> bool:
        """False when one of the two convolutions' parameters changed since they were quantised."""
        return _versions(self.params) == self._versions

    def __call__(self, feat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.conv(self.conv.quantize(feat.contiguous(memory_format=torch.channels_last)))
        return out[:, :self.split], torch.tanh(out[:, self.split:])


def _versions(params: list[torch.Tensor]) -> list[tuple[int, int]]:
    """(id, version counter) of each parameter not made under inference mode (those have no version)."""
    return [(id(p), p._version) for p in params if not p.is_inference()]


def supported_gru_init(model: nn.Module) -> bool:
    """Whether :class:`Int8GruInit` knows the model's GRU start: a 3x3 static convolution and ``HiddenInit``."""
    static = getattr(getattr(model, "update_block", None), "static", None)
    hidden = getattr(getattr(model, "hidden_init", None), "conv", None)
    return (type(static) is nn.Conv2d and type(hidden) is nn.Conv2d and static.kernel_size == hidden.kernel_size
            and static.padding == hidden.padding and static.stride == hidden.stride == (1, 1)
            and static.in_channels == hidden.in_channels)


def supported(encoder: nn.Module) -> bool:
    """Whether :class:`Int8Encoder` knows ``encoder``: a ``FeatureEncoder`` of residual blocks with instance norms."""
    if type(encoder) is not FeatureEncoder:
        return False
    blocks = [block for layer in (encoder.layer1, encoder.layer2, encoder.layer3) for block in layer]
    return type(encoder.stem[1]) is InstanceNorm2d and all(
        type(block) is ResidualBlock and type(block.norm1) is InstanceNorm2d
        and type(block.norm2) is InstanceNorm2d for block in blocks)
