"""E1 / E2 / E4 (docs/registrations.md): version 15 with cheaper encoder stages, distilled blockwise on the CPU.

E1: the encoder's ``layer1`` (two residual blocks of 64 channels at 1/2 resolution, about a third of the default's
CPU pass) is replaced by two depthwise-separable residual blocks (``SeparableBlock``), trained alone to reproduce
``layer1``'s output and the encoder's output (everything else frozen as shipped). E4 (``--stage both``): both
stages, ``layer2`` (1/4 resolution, 64 -> 96) replaced the same way, distilled jointly against version 15's
``layer1``, ``layer2`` and encoder outputs (``--stage 2``: ``layer2`` alone on E1's kept, frozen first stage).
Steps, each writing under ``--run`` or ``--out`` and resumable:

``train``: the distillation, ``--minutes`` of CPU in total over any number of calls -> RUN/state.pt, RUN/log.jsonl.
``score``: the student in version 15 on a validation set -> OUT/gtfree.json (``optstereo.validation.score``).
``keep``: the students alone as a small safetensors file (commit it with ``git add -f``, then remove it from the
    tree and name the commit in results/cheap_layer1/weights.json: candidate weights live in git history).
``export``: version 15 with the student as one safetensors file (``ModelConfig.stage1 = "separable"``).
``time``: seconds per KITTI 2015 frame of version 15 and of the student (the engineered pass, 2 threads),
    each beside OpenCV SGBM-HH frame by frame as T1 times them -> OUT/timing.json.

    python -m pipelines.studies.cheap_layer1 train --run /work/runs/e1 --minutes 40
    python -m pipelines.studies.cheap_layer1 score --state /work/runs/e1/state.pt --valset /work/valset --out DIR
    python -m pipelines.studies.cheap_layer1 time --state /work/runs/e1/state.pt --out results/cheap_layer1
    python -m pipelines.studies.cheap_layer1 train --run /work/runs/e4 --minutes 60 --stage both \
        --images ../shared/data/kitti_unlabelled ../shared/data/unlabelled_more
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
from optstereo.models.extractor import FeatureEncoder, make_stage
from optstereo.models.optstereo import normalize_image
from optstereo.validation import open_valset, score, write_report
from pipelines.bench_labeler import _opencv
from pipelines.bench_models import THREADS, _frames, beside_sgbm

BASE = "pretrained"
PACKS = tuple(Path("/work/pack") / name for name in ("shared", "extra", "more", "tabletop_half"))
CROP = (320, 640)
BATCH = 2
STAGE_RUNS = ("1", "2", "both")  # what a run trains: E1's layer1, layer2 on E1's, both jointly (E4)
FINAL_LR_FRACTION = 0.8  # the last 20 % of the budget at lr / 10
SAVE_EVERY_S = 120.0


def student(channels: int = 64, out_channels: int | None = None) -> nn.Sequential:
    """E1's ``layer1`` (two ``SeparableBlock`` of ``channels``, ``ModelConfig.stage1 = "separable"``) or, with
    ``out_channels``, E4's ``layer2`` (a strided block ``channels`` -> ``out_channels``, then one of
    ``out_channels``: ``ModelConfig.stage2 = "separable"``)."""
    if out_channels is None:
        return make_stage("stage1", "separable", channels, channels, stride=1)
    return make_stage("stage2", "separable", channels, out_channels, stride=2)


def image_files(roots: tuple[Path, ...], size: tuple[int, int] = CROP) -> tuple[list[Path], int]:
    """Every .png / .jpg under ``roots`` (recursively) at least ``size`` large, and how many smaller ones were
    skipped. Raises FileNotFoundError naming the roots when none is left."""
    found = sorted(p for root in roots for p in Path(root).rglob("*") if p.suffix.lower() in (".png", ".jpg"))
    kept = []
    for path in found:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise OSError(f"{path}: not a readable image")
        if image.shape[0] >= size[0] and image.shape[1] >= size[1]:
            kept.append(path)
    if not kept:
        raise FileNotFoundError(f"no image of at least {size} under {[str(r) for r in roots]}")
    return kept, len(found) - len(kept)


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


def relative_mse(parts: dict[str, tuple[torch.Tensor, torch.Tensor]]) -> tuple[torch.Tensor, dict[str, float]]:
    """The distillation losses' sum of MSEs, each over its target's variance: {name: (output, target)} -> (loss,
    each part as a float)."""
    losses = {name: F.mse_loss(out, ref) / ref.var() for name, (out, ref) in parts.items()}
    return sum(losses.values()), {name: float(loss.detach()) for name, loss in losses.items()}


def after_layer1(encoder: FeatureEncoder, x: torch.Tensor) -> torch.Tensor:
    """The encoder's stages after ``layer1``: (B, 64, H/2, W/2) -> (B, C, H/8, W/8)."""
    return encoder.proj(encoder.layer3(encoder.layer2(x)))


def after_layer2(encoder: FeatureEncoder, x: torch.Tensor) -> torch.Tensor:
    """The encoder's stages after ``layer2``: (B, 96, H/4, W/4) -> (B, C, H/8, W/8)."""
    return encoder.proj(encoder.layer3(x))


def distill_loss_stage2(encoder: FeatureEncoder, stage1: nn.Module, layer: nn.Module,
                        images: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
    """E4's loss on (B, 3, H, W) normalised images: ``layer`` on ``stage1``'s features (E1's first stage, frozen)
    against ``encoder.layer2`` on the encoder's own ``layer1``: MSE over the target's variance, plus the same for
    the encoder's output; (loss, its two parts)."""
    with torch.no_grad():
        stem = encoder.stem(images)
        target2 = encoder.layer2(encoder.layer1(stem))
        target = after_layer2(encoder, target2)
        features = stage1(stem)
    out2 = layer(features)
    return relative_mse({"layer2": (out2, target2), "encoder": (after_layer2(encoder, out2), target)})


def distill_loss_both(encoder: FeatureEncoder, layers: nn.ModuleDict,
                      images: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
    """E4's joint loss: ``layers["layer1"]`` against ``encoder.layer1``, ``layers["layer2"]`` on the student's
    first stage against ``encoder.layer2`` on its own, and the encoder's output; each MSE over its target's
    variance; (loss, its three parts)."""
    with torch.no_grad():
        stem = encoder.stem(images)
        target1 = encoder.layer1(stem)
        target2 = encoder.layer2(target1)
        target = after_layer2(encoder, target2)
    out1 = layers["layer1"](stem)
    out2 = layers["layer2"](out1)
    return relative_mse({"layer1": (out1, target1), "layer2": (out2, target2),
                         "encoder": (after_layer2(encoder, out2), target)})


def frozen_stage1(path: str | Path, channels: int) -> nn.Sequential:
    """E1's kept first stage (``keep``'s safetensors file), frozen."""
    stage1 = student(channels)
    stage1.load_state_dict(load_file(str(path)))
    stage1.eval().requires_grad_(False)
    return stage1


def distill_loss(encoder: FeatureEncoder, layer: nn.Module,
                 images: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
    """E1's loss on (B, 3, H, W) normalised images: MSE of ``layer``'s output against ``encoder.layer1``'s over the
    latter's variance, plus the same for the encoder's output; (loss, its two parts)."""
    with torch.no_grad():
        stem = encoder.stem(images)
        target1 = encoder.layer1(stem)
        target = after_layer1(encoder, target1)
    out1 = layer(stem)
    return relative_mse({"layer1": (out1, target1), "encoder": (after_layer1(encoder, out1), target)})


def frozen_encoder(base: str | Path = BASE) -> FeatureEncoder:
    """Version 15's encoder, every parameter frozen."""
    encoder = load_model(base).feature_encoder.eval()
    encoder.requires_grad_(False)
    return encoder


def train(run: Path, minutes: float, lr: float = 1e-3, seed: int = 0, threads: int = THREADS,
          packs: tuple[Path, ...] = PACKS, base: str | Path = BASE, size: tuple[int, int] = CROP,
          stage: str = "1", images: tuple[Path, ...] = (), stage1_state: str | Path | None = None) -> Path:
    """Distil E1's ``layer1`` (``stage`` "1"), ``layer2`` on E1's frozen first stage ``stage1_state`` ("2") or
    both stages jointly (E4: "both") for ``minutes`` of wall time in total (resumed from RUN/state.pt when
    present). Images: every one under ``images`` at least ``size`` large when given, else the left and right
    images of ``packs``."""
    if stage not in STAGE_RUNS:
        raise ValueError(f"stage must be one of {STAGE_RUNS}, got {stage!r}")
    torch.set_num_threads(threads)
    torch.manual_seed(seed)
    run.mkdir(parents=True, exist_ok=True)
    encoder = frozen_encoder(base)
    if images:
        paths, skipped = image_files(images, size)
        print(f"{len(paths)} images, {skipped} smaller than {size} skipped", flush=True)
    else:
        paths = image_paths(packs)
    width1 = encoder.layer1[0].conv1.out_channels
    width2 = encoder.layer2[0].conv1.out_channels
    if stage == "2" and stage1_state is None:
        raise ValueError("stage 2 trains on a kept first stage: give stage1_state (cheap_layer1 keep's file)")
    stage1 = frozen_stage1(stage1_state, width1) if stage == "2" else None
    layer: nn.Module = {"1": lambda: student(width1), "2": lambda: student(width1, width2),
                        "both": lambda: nn.ModuleDict({"layer1": student(width1),
                                                       "layer2": student(width1, width2)})}[stage]()
    opt = torch.optim.Adam(layer.parameters(), lr=lr)
    step, elapsed = 0, 0.0
    state_path = run / "state.pt"
    if state_path.exists():
        saved = torch.load(state_path, weights_only=False)
        if str(saved.get("stage", 1)) != stage:
            raise ValueError(f"{state_path}: a stage-{saved.get('stage', 1)} run, not stage {stage}")
        layer.load_state_dict(saved["layer"])
        opt.load_state_dict(saved["optimizer"])
        step, elapsed = saved["step"], saved["elapsed_s"]
    rng = random.Random(seed * 1_000_003 + step)  # a resumed run draws new crops, reproducibly
    budget, start, last_save = minutes * 60.0, time.monotonic() - elapsed, time.monotonic()
    extra = {"stage": stage, **({"stage1": stage1.state_dict()} if stage1 is not None else {})}
    with (run / "log.jsonl").open("a") as log:
        while (elapsed := time.monotonic() - start) < budget:
            for group in opt.param_groups:
                group["lr"] = lr if elapsed < FINAL_LR_FRACTION * budget else lr / 10
            batch = crops(paths, rng, size=size)
            if stage == "both":
                loss, parts = distill_loss_both(encoder, layer, batch)
            elif stage1 is not None:
                loss, parts = distill_loss_stage2(encoder, stage1, layer, batch)
            else:
                loss, parts = distill_loss(encoder, layer, batch)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            step += 1
            log.write(json.dumps({"step": step, "elapsed_s": round(elapsed, 1), "loss": loss.item(), **parts}) + "\n")
            if time.monotonic() - last_save > SAVE_EVERY_S:
                _save(state_path, layer, opt, step, elapsed, extra)
                last_save = time.monotonic()
                log.flush()
                print(f"step {step}, {elapsed / 60:.1f} min, loss {loss.item():.4f} {parts}", flush=True)
    _save(state_path, layer, opt, step, time.monotonic() - start, extra)
    return state_path


def _save(path: Path, layer: nn.Module, opt: torch.optim.Optimizer, step: int, elapsed: float,
          extra: dict[str, Any] | None = None) -> None:
    """Atomically write the student, its optimizer and the run's counters (and a stage-2 run's frozen stage 1)."""
    tmp = path.with_suffix(".tmp")
    torch.save({"layer": layer.state_dict(), "optimizer": opt.state_dict(), "step": step, "elapsed_s": elapsed,
                **(extra or {})}, tmp)
    tmp.rename(path)


def _stages(state: str | Path) -> dict[str, dict[str, torch.Tensor]]:
    """The students of a run's state.pt or of ``keep``'s file: {"layer1": ...} or {"layer1": ..., "layer2": ...}."""
    if Path(state).suffix == ".safetensors":
        flat = load_file(str(state))
        if not any(k.startswith("layer2.") for k in flat):
            return {"layer1": flat}  # E1's file: the first stage's keys alone
        return {name: {k[len(name) + 1:]: v for k, v in flat.items() if k.startswith(name + ".")}
                for name in ("layer1", "layer2")}
    saved = torch.load(state, weights_only=False)
    stage = str(saved.get("stage", 1))
    if stage == "2":
        return {"layer1": saved["stage1"], "layer2": saved["layer"]}
    if stage == "both":
        return {name: {k[len(name) + 1:]: v for k, v in saved["layer"].items() if k.startswith(name + ".")}
                for name in ("layer1", "layer2")}
    return {"layer1": saved["layer"]}


def student_model(state: str | Path, base: str | Path = BASE) -> nn.Module:
    """Version 15 with ``layer1`` (and, for E4, ``layer2``) replaced by the students of a ``train`` run (its
    state.pt, or the students alone as written by ``keep``: results/cheap_layer1/weights.json names them),
    engineered for the CPU as ``load_model`` gives the default."""
    model = load_model(base)
    encoder = model.feature_encoder
    width1, width2 = encoder.layer1[0].conv1.out_channels, encoder.layer2[0].conv1.out_channels
    for name, weights in _stages(state).items():
        layer = student(width1) if name == "layer1" else student(width1, width2)
        layer.load_state_dict(weights)
        setattr(encoder, name, layer.to(memory_format=torch.channels_last))
    return model


def keep(state: Path, out: Path) -> Path:
    """The students of a run's state.pt alone (no optimizer), as safetensors: the small file worth committing
    (E1: the first stage's keys as they are; E4: both stages, prefixed ``layer1.`` / ``layer2.``)."""
    stages = _stages(state)
    flat = (stages["layer1"] if len(stages) == 1
            else {f"{name}.{k}": v for name, weights in stages.items() for k, v in weights.items()})
    save_file({k: v.contiguous() for k, v in flat.items()}, str(out))
    return out


def export(state: Path, out: Path, base: str | Path = BASE, scale: float | None = None) -> Path:
    """``base``'s weights and inference settings (version 15) with the students as the encoder's separable stages
    (``stage1`` and, for E4, ``stage2 = "separable"``) and the input ``scale`` when given, as one safetensors
    file: the product builds it as it builds any other."""
    model = student_model(state, base)
    stages = _stages(state)
    config = dict(model.config.to_dict(), stage1="separable",
                  stage2="separable" if "layer2" in stages else "residual")
    built = build_from_config(config)
    built.load_state_dict(model.state_dict())
    built.inference_config = model_inference(model)
    if scale is not None:
        built.inference_config = built.inference_config.replace(scale=scale)
    step = torch.load(state, weights_only=False)["step"] if Path(state).suffix != ".safetensors" else 0
    return export_safetensors(out, built, step=step)


def time_models(models: dict[str, nn.Module], shared: Path, repeats: int) -> dict[str, dict[str, Any]]:
    """Per model: median seconds per KITTI 2015 frame and the median per-frame ratio to SGBM-HH timed beside it
    (``pipelines.bench_models.beside_sgbm``, T1's timing)."""
    torch.set_num_threads(THREADS)
    sgbm, frames = _opencv(cv2.STEREO_SGBM_MODE_HH), _frames(shared)
    return {name: beside_sgbm(model, frames, repeats, sgbm) for name, model in models.items()}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    sub = parser.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train")
    t.add_argument("--run", type=Path, required=True)
    t.add_argument("--minutes", type=float, default=40.0)
    t.add_argument("--stage", choices=STAGE_RUNS, default="1",
                   help="1: E1's layer1; 2: layer2 on E1's frozen layer1; both: both jointly (E4)")
    t.add_argument("--images", type=Path, nargs="*", default=[], help="image folders (default: E1's packs)")
    t.add_argument("--stage1-state", type=Path, default=None, help="stage 2: E1's kept first stage (keep's file)")
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
    m.add_argument("--against", type=Path, default=None,
                   help="another student (E1's file) timed in the same run at --scales too")
    x = sub.add_parser("export")
    x.add_argument("--state", type=Path, required=True)
    x.add_argument("--out", type=Path, required=True)
    x.add_argument("--scale", type=float, default=None, help="the file's input scale (default: version 15's)")
    k = sub.add_parser("keep", help="the student alone -> a small safetensors file")
    k.add_argument("--state", type=Path, required=True)
    k.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if args.cmd == "keep":
        print(keep(args.state, args.out))
    elif args.cmd == "export":
        print(export(args.state, args.out, scale=args.scale))
    elif args.cmd == "train":
        print(train(args.run, args.minutes, stage=args.stage, images=tuple(args.images),
                    stage1_state=args.stage1_state))
    elif args.cmd == "score":
        torch.set_num_threads(THREADS)
        model = student_model(args.state)
        if args.scale is not None:
            model.inference_config = model.inference_config.replace(scale=args.scale)
        result = score(model, open_valset(args.valset), progress=True, what="student")
        write_report(result, args.out, f"version 15 + the separable stages of {args.state}", args.valset,
                     scale=args.scale)
        print(result.summary)
    else:
        students = {"student": args.state} if args.against is None else {"e1": args.against, "student": args.state}
        models = {"v15": load_model(BASE), **{name: student_model(path) for name, path in students.items()}}
        for scale in args.scales:
            for name, path in students.items():
                models[f"{name}_s{scale:g}"] = student_model(path)
                models[f"{name}_s{scale:g}"].inference_config = models[name].inference_config.replace(scale=scale)
        result = time_models(models, args.shared, args.repeats)
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / f"{args.name}.json").write_text(json.dumps(result, indent=2) + "\n")
        for name, row in result.items():
            print(f"{name}: {row['s_per_frame']:.2f} s per frame, {row['ratio']:.2f}x SGBM-HH", flush=True)


if __name__ == "__main__":
    main()
