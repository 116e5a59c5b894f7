"""Measuring a weights file's int8 clips (:mod:`optstereo.inference.int8`) on unlabelled pairs, and the command.

``python -m optstereo.inference.int8_calibration --checkpoint FILE --root DIR [--root DIR ...]`` measures the clips
of every int8 convolution on pairs under the roots (every KITTI-style pair, the ``kitti_unlabelled`` reader: their GT
is never read), ``--pairs`` of them evenly spread (12), and writes ``FILE.int8.json``. The shipped default's were
measured with ``--checkpoint pretrained --root ../shared/data/kitti_unlabelled --root ../shared/data/unlabelled_more``.
``optstereo-adapt`` measures its adapted weights' clips on the rig's training frames (:func:`inherit_clips`).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import torch
from torch import nn

from optstereo.api import load_model
from optstereo.inference import int8
from optstereo.inference.engine import model_inference_config, run
from optstereo.inference.fastpath import engineering
from optstereo.pretrained import resolve_checkpoint_spec
from pvm_labeler.common.datasets import discover, load_pair

#: Values sampled per convolution input and image (the quantile of a random sample).
CALIBRATION_SAMPLES = 400_000
#: Pairs measured by default (the shipped default's clips: 12 unlabelled pairs).
PAIRS = 12
Pair = tuple[Any, Any]


def spread(items: list[Any], count: int) -> list[Any]:
    """``count`` items evenly spaced over ``items`` (all of them when there are fewer)."""
    if count >= len(items):
        return list(items)
    step = len(items) / count
    return [items[int(i * step)] for i in range(count)]


def calibrate(model: nn.Module, pairs: Iterable[tuple[Any, Any]], quantile: float = int8.CLIP_QUANTILE,
              seed: int = 0) -> dict[str, float]:
    """Clip per int8 convolution of the encoder (:func:`measure`'s first part)."""
    return measure(model, pairs, quantile, seed)[0]


def measure(model: nn.Module, pairs: Iterable[tuple[Any, Any]], quantile: float = int8.CLIP_QUANTILE,
            seed: int = 0) -> tuple[dict[str, float], dict[str, tuple[float, float]]]:
    """From the float32 pass over ``pairs`` ((H, W, 3) uint8 left and right), a random sample of
    :data:`CALIBRATION_SAMPLES` values of each input per call: (clips: encoder convolution -> the mean ``quantile`` of
    its input; ranges: ``gru_init`` -> the mean (1 - ``quantile``, ``quantile``) quantiles of F_l, when the model's
    GRU start is one :class:`~optstereo.inference.int8.Int8GruInit` knows). F_l has its own random stream, so the
    clips are the same with or without it."""
    encoder = model.feature_encoder
    modules = dict(encoder.named_modules())
    generator, f_generator = torch.Generator().manual_seed(seed), torch.Generator().manual_seed(seed + 1)
    values: dict[str, list[float]] = {name: [] for name in int8.conv_names(encoder)}
    f_values: list[tuple[float, float]] = []

    def sample(x: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
        flat = x.detach().reshape(-1)
        return flat[torch.randint(0, flat.numel(), (CALIBRATION_SAMPLES,), generator=gen)].float()

    def hook(name: str) -> Any:
        def record(_module: nn.Module, inputs: tuple[torch.Tensor, ...], _output: torch.Tensor) -> None:
            values[name].append(float(torch.quantile(sample(inputs[0], generator), quantile)))
        return record

    def record_f(_module: nn.Module, inputs: tuple[torch.Tensor, ...], _output: torch.Tensor) -> None:
        xs = sample(inputs[0], f_generator)
        f_values.append((float(torch.quantile(xs, 1.0 - quantile)), float(torch.quantile(xs, quantile))))

    handles = [modules[name].register_forward_hook(hook(name)) for name in values]
    if int8.supported_gru_init(model):
        handles.append(model.hidden_init.conv.register_forward_hook(record_f))
    try:
        # the file's scale and adaptive pass, not the pixel budget: which passes a calibrating pair takes (and so the
        # clips) must not move when only ``enlarge_max`` or ``shrink_large`` does, so the default's clips stay those
        # it was judged with
        config = model_inference_config(model).replace(enlarge_max=1.0, shrink_large=False)
        with engineering(False):
            for left, right in pairs:
                run(model, left, right, config)
    finally:
        for handle in handles:
            handle.remove()
    empty = [name for name, v in values.items() if not v]
    if empty:
        raise ValueError(f"calibration saw no input of {empty[:3]}: were any pairs given?")
    clips = {name: max(sum(v) / len(v), 1e-6) for name, v in values.items()}
    ranges = {}
    if f_values:
        low = min(sum(v[0] for v in f_values) / len(f_values), -1e-6)
        ranges["gru_init"] = (low, max(sum(v[1] for v in f_values) / len(f_values), 1e-6))
    return clips, ranges


def calibrate_file(weights: Path, pairs: list[Pair], quantile: float = int8.CLIP_QUANTILE) -> Path | None:
    """Measure ``weights``' clips on ``pairs`` and write them beside it; None (nothing written) when its encoder is
    not one the int8 path knows."""
    model = load_model(weights, "cpu")
    encoder = getattr(model, "feature_encoder", None)
    if encoder is None or not int8.supported(encoder) or not pairs:
        return None
    clips, ranges = measure(model, pairs, quantile)
    return int8.write_sidecar(weights, int8.Int8Calibration(clips, int8.file_sha256(weights), quantile, len(pairs),
                                                            ranges))


def inherit_clips(kept: Path, start: Path, kept_is_start: bool, pairs: Callable[[], list[Pair]]) -> Path | None:
    """Clips for ``kept``, a model made from ``start`` (``optstereo-adapt``'s kept checkpoint), only when ``start``
    has clips of its own (int8 was checked for it) and this CPU runs int8: ``start``'s clips when ``kept`` is a byte
    copy of it, else measured on ``pairs()`` (the rig's training frames). None otherwise."""
    start_clips = int8.read_sidecar(start)
    if start_clips is None or not int8.available():
        return None
    if kept_is_start:
        return int8.write_sidecar(kept, start_clips)
    return calibrate_file(kept, pairs(), start_clips.quantile)


def main(argv: list[str] | None = None) -> None:
    """The command (module doc)."""
    parser = argparse.ArgumentParser(prog="python -m optstereo.inference.int8_calibration", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", required=True, help="a .safetensors / .pt file or a shipped name")
    parser.add_argument("--root", type=Path, action="append", required=True,
                        help="a folder of KITTI-style pairs (image_2 / image_3 at any depth); repeatable")
    parser.add_argument("--pairs", type=int, default=PAIRS, help="pairs measured, evenly spread over the sorted list")
    args = parser.parse_args(argv)
    weights = resolve_checkpoint_spec(args.checkpoint)
    refs = sorted((ref for root in args.root for ref in discover("kitti_unlabelled", root)),
                  key=lambda ref: str(ref.left))
    chosen = spread(refs, args.pairs)
    if not chosen:
        raise SystemExit(f"no pairs found under {', '.join(map(str, args.root))}")
    samples = [load_pair(ref) for ref in chosen]
    path = calibrate_file(weights, [(s.left, s.right) for s in samples])
    if path is None:
        raise SystemExit(f"{weights}: its encoder is not one the int8 path knows (optstereo.inference.int8.supported)")
    print(f"wrote {path}: clips of {len(int8.read_sidecar(weights).clips)} convolutions from {len(chosen)} pairs")


if __name__ == "__main__":
    main()
