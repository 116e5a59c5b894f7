"""E1 / E2 (docs/registrations.md): version 15 with a cheaper first encoder stage, distilled blockwise on the CPU.

The encoder's ``layer1`` (two residual blocks of 64 channels at 1/2 resolution, about a third of the default's
CPU pass) is replaced by two depthwise-separable residual blocks (:class:`SepBlock`), trained alone to reproduce
``layer1``'s output and the encoder's output (everything else frozen as shipped). Steps, each writing under ``--run``
or ``--out`` and resumable:

``train``: the distillation, ``--minutes`` of CPU in total over any number of calls -> RUN/state.pt, RUN/log.jsonl.
``score``: the student in version 15 on a validation set -> OUT/gtfree.json (``optstereo.validation.score``).
``keep``: the student alone as a small safetensors file (results/cheap_layer1/e1_stage1.safetensors).
``export``: version 15 with the student as one safetensors file (``ModelConfig.stage1 = "separable"``).
``time``: seconds per KITTI 2015 frame of version 15 and of the student (the engineered pass, 2 threads),
    each beside OpenCV SGBM-HH frame by frame as T1 times them -> OUT/timing.json.

    python -m pipelines.studies.cheap_layer1 train --run /work/runs/e1 --minutes 40
    python -m pipelines.studies.cheap_layer1 score --state /work/runs/e1/state.pt --valset /work/valset --out DIR
    python -m pipelines.studies.cheap_layer1 time --state /work/runs/e1/state.pt --out results/cheap_layer1
"""

from __future__ import annotations

import argparse
import json
import random
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save_file
from torch import nn

from optstereo.api import load_model
from optstereo.checkpoint import export_safetensors, model_inference
from optstereo.models import build_from_config
from optstereo.models.extractor import FeatureEncoder
from optstereo.models.layers import SeparableBlock
from optstereo.models.optstereo import normalize_image
from optstereo.validation import open_valset, score, write_report
from pipelines.bench_labeler import _opencv
from pipelines.bench_models import THREADS, _frames, beside_sgbm

BASE = "pretrained"
PACKS = tuple(Path("/work/pack") / name for name in ("shared", "extra", "more", "tabletop_half"))
CROP = (320, 640)
BATCH = 2
FINAL_LR_FRACTION = 0.8  # the last 20 % of the budget at lr / 10
SAVE_EVERY_S = 120.0


def student(channels: int = 64) -> nn.Sequential:
    """E1's ``layer1``: two ``SeparableBlock`` of ``channels`` (the product's, ``ModelConfig.stage1 = "separable"``)."""
    return nn.Sequential(SeparableBlock(channels), SeparableBlock(channels))


def image_paths(packs: tuple[Path, ...] = PACKS) -> list[Path]:
    """Every left and right image of the training packs (no validation pair is in them)."""
    paths = sorted(p for pack in packs for side in ("left", "right") for p in (pack / side).iterdir())
    if not paths:
        raise FileNotFoundError(f"no images under {[str(p) for p in packs]}")
    return paths


def crops(paths: list[Path], rng: random.Random, batch: int = BATCH, size: tuple[int, int] = CROP) -> torch.Tensor:
    """``batch`` random ``size`` crops of random images, flipped left-right with p = 0.5 -> (B, 3, h, w) float32 in
    [-1, 1] (``normalize_image``)."""
    out = []
    for _ in range(batch):
        path = rng.choice(paths)
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise OSError(f"{path}: not a readable image")
        h, w = size
        if image.shape[0] < h or image.shape[1] < w:
            raise ValueError(f"{path}: {image.shape[:2]} is smaller than the crop {size}")
        y, x = rng.randrange(image.shape[0] - h + 1), rng.randrange(image.shape[1] - w + 1)
        crop = image[y:y + h, x:x + w, ::-1]
        if rng.random() < 0.5:
            crop = crop[:, ::-1]
        out.append(torch.from_numpy(np.ascontiguousarray(crop)).permute(2, 0, 1).float())
    return normalize_image(torch.stack(out))


def after_layer1(encoder: FeatureEncoder, x: torch.Tensor) -> torch.Tensor:
    """The encoder's stages after ``layer1``: (B, 64, H/2, W/2) -> (B, C, H/8, W/8)."""
    return encoder.proj(encoder.layer3(encoder.layer2(x)))


def distill_loss(encoder: FeatureEncoder, layer: nn.Module,
                 images: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
    """E1's loss on (B, 3, H, W) normalised images: MSE of ``layer``'s output against ``encoder.layer1``'s over the
    latter's variance, plus the same for the encoder's output; (loss, its two parts)."""
    with torch.no_grad():
        stem = encoder.stem(images)
        target1 = encoder.layer1(stem)
        target = after_layer1(encoder, target1)
    out1 = layer(stem)
    part1 = F.mse_loss(out1, target1) / target1.var()
    part2 = F.mse_loss(after_layer1(encoder, out1), target) / target.var()
    return part1 + part2, {"layer1": float(part1.detach()), "encoder": float(part2.detach())}


def frozen_encoder(base: str | Path = BASE) -> FeatureEncoder:
    """Version 15's encoder, every parameter frozen."""
    encoder = load_model(base).feature_encoder.eval()
    encoder.requires_grad_(False)
    return encoder


def train(run: Path, minutes: float, lr: float = 1e-3, seed: int = 0, threads: int = THREADS,
          packs: tuple[Path, ...] = PACKS, base: str | Path = BASE, size: tuple[int, int] = CROP) -> Path:
    """Distil E1's ``layer1`` for ``minutes`` of wall time in total (resumed from RUN/state.pt when present)."""
    torch.set_num_threads(threads)
    torch.manual_seed(seed)
    run.mkdir(parents=True, exist_ok=True)
    encoder, paths = frozen_encoder(base), image_paths(packs)
    layer = student(encoder.layer1[0].conv1.out_channels)
    opt = torch.optim.Adam(layer.parameters(), lr=lr)
    step, elapsed = 0, 0.0
    state_path = run / "state.pt"
    if state_path.exists():
        saved = torch.load(state_path, weights_only=False)
        layer.load_state_dict(saved["layer"])
        opt.load_state_dict(saved["optimizer"])
        step, elapsed = saved["step"], saved["elapsed_s"]
    rng = random.Random(seed * 1_000_003 + step)  # a resumed run draws new crops, reproducibly
    budget, start, last_save = minutes * 60.0, time.monotonic() - elapsed, time.monotonic()
    with (run / "log.jsonl").open("a") as log:
        while (elapsed := time.monotonic() - start) < budget:
            for group in opt.param_groups:
                group["lr"] = lr if elapsed < FINAL_LR_FRACTION * budget else lr / 10
            loss, parts = distill_loss(encoder, layer, crops(paths, rng, size=size))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            step += 1
            log.write(json.dumps({"step": step, "elapsed_s": round(elapsed, 1), "loss": loss.item(), **parts}) + "\n")
            if time.monotonic() - last_save > SAVE_EVERY_S:
                _save(state_path, layer, opt, step, elapsed)
                last_save = time.monotonic()
                log.flush()
                print(f"step {step}, {elapsed / 60:.1f} min, loss {loss.item():.4f} {parts}", flush=True)
    _save(state_path, layer, opt, step, time.monotonic() - start)
    return state_path


def _save(path: Path, layer: nn.Module, opt: torch.optim.Optimizer, step: int, elapsed: float) -> None:
    """Atomically write the student, its optimizer and the run's counters."""
    tmp = path.with_suffix(".tmp")
    torch.save({"layer": layer.state_dict(), "optimizer": opt.state_dict(), "step": step, "elapsed_s": elapsed}, tmp)
    tmp.rename(path)


def student_model(state: Path, base: str | Path = BASE) -> nn.Module:
    """Version 15 with ``layer1`` replaced by the student of a ``train`` run (its state.pt, or the student alone as
    written by ``keep``: results/cheap_layer1/e1_stage1.safetensors), engineered for the CPU as
    ``load_model`` gives the default (the engineered encoder calls blocks it does not know as they are)."""
    model = load_model(base)
    layer = student(model.feature_encoder.layer1[0].conv1.out_channels)
    layer.load_state_dict(load_file(state) if Path(state).suffix == ".safetensors"
                          else torch.load(state, weights_only=False)["layer"])
    model.feature_encoder.layer1 = layer.to(memory_format=torch.channels_last)
    return model


def keep(state: Path, out: Path) -> Path:
    """The student of a run's state.pt alone (no optimizer), as safetensors: the small file worth committing."""
    save_file({k: v.contiguous() for k, v in torch.load(state, weights_only=False)["layer"].items()}, str(out))
    return out


def export(state: Path, out: Path, base: str | Path = BASE) -> Path:
    """``base``'s weights and inference settings (version 15) with the student as the encoder's first stage
    (``stage1 = "separable"``), as one safetensors file: the product builds it as it builds any other."""
    model = student_model(state, base)
    config = dict(model.config.to_dict(), stage1="separable")
    built = build_from_config(config)
    built.load_state_dict(model.state_dict())
    built.inference_config = model_inference(model)
    return export_safetensors(out, built, step=torch.load(state, weights_only=False)["step"])


def time_models(models: dict[str, nn.Module], shared: Path, repeats: int) -> dict[str, dict[str, Any]]:
    """Per model: median seconds per KITTI 2015 frame and the median per-frame ratio to SGBM-HH timed beside it
    (``pipelines.bench_models.beside_sgbm``, T1's timing)."""
    torch.set_num_threads(THREADS)
    sgbm, frames = _opencv(cv2.STEREO_SGBM_MODE_HH), _frames(shared)
    return {name: beside_sgbm(model, frames, repeats, sgbm) for name, model in models.items()}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train")
    t.add_argument("--run", type=Path, required=True)
    t.add_argument("--minutes", type=float, default=40.0)
    s = sub.add_parser("score")
    s.add_argument("--state", type=Path, required=True)
    s.add_argument("--valset", type=Path, required=True)
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--scale", type=float, default=None, help="input scale (E2: 1.125; default: the file's)")
    m = sub.add_parser("time")
    m.add_argument("--state", type=Path, required=True)
    m.add_argument("--out", type=Path, required=True)
    m.add_argument("--shared", type=Path, default=Path("../shared/data"))
    m.add_argument("--repeats", type=int, default=3)
    m.add_argument("--scales", type=float, nargs="*", default=[], help="E1 also at these input scales (E2: 1.125)")
    m.add_argument("--name", default="timing", help="OUT/NAME.json")
    x = sub.add_parser("export")
    x.add_argument("--state", type=Path, required=True)
    x.add_argument("--out", type=Path, required=True)
    k = sub.add_parser("keep", help="the student alone -> a small safetensors file")
    k.add_argument("--state", type=Path, required=True)
    k.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if args.cmd == "keep":
        print(keep(args.state, args.out))
    elif args.cmd == "export":
        print(export(args.state, args.out))
    elif args.cmd == "train":
        print(train(args.run, args.minutes))
    elif args.cmd == "score":
        torch.set_num_threads(THREADS)
        model = student_model(args.state)
        if args.scale is not None:
            model.inference_config = model.inference_config.replace(scale=args.scale)
        result = score(model, open_valset(args.valset), progress=True, what="E1")
        write_report(result, args.out, f"version 15 + layer1 of {args.state}", args.valset, scale=args.scale)
        print(result.summary)
    else:
        models = {"v15": load_model(BASE), "e1": student_model(args.state)}
        for scale in args.scales:
            models[f"e1_s{scale:g}"] = student_model(args.state)
            models[f"e1_s{scale:g}"].inference_config = models["e1"].inference_config.replace(scale=scale)
        result = time_models(models, args.shared, args.repeats)
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / f"{args.name}.json").write_text(json.dumps(result, indent=2) + "\n")
        for name, row in result.items():
            print(f"{name}: {row['s_per_frame']:.2f} s per frame, {row['ratio']:.2f}x SGBM-HH", flush=True)


if __name__ == "__main__":
    main()
