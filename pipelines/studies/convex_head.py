"""U1 (docs/registrations.md): RAFT's convex upsampler on version 15, its mask head trained alone on the CPU.

Every other weight of version 15 stays as shipped, so the GRU's final 1/8 disparity D_s and hidden state h of a pair
never change: ``cache`` runs version 15 once per training pair (its own inference: scale 1, N_s = 8, the pair
padded as ``optstereo.inference.engine`` pads it) and keeps what its upsampler receives; ``train`` fits the mask head
of ``ConvexUpsampler`` to the pair's labels (PVM's, with the teacher's fills at their confidence) by L_P's
confidence-weighted Huber on the full-resolution disparity; ``export`` writes version 15's weights with the new
upsampler as one safetensors file (its model config says ``upsampler: convex``). Resumable: ``cache`` skips pairs
done, ``train`` continues from its last state.

    python -m pipelines.studies.convex_head cache --labels SHARDS --cache DIR
    python -m pipelines.studies.convex_head train --cache DIR --run RUN --minutes 30
    python -m pipelines.studies.convex_head export --run RUN --out FILE.safetensors
    python -m pipelines.studies.convex_head time v15=pretrained u1=FILE.safetensors --out timing.json
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import random
import statistics
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch import nn

from optstereo.api import load_model
from optstereo.checkpoint import export_safetensors, model_inference
from optstereo.inference.engine import infer, to_batch
from optstereo.inference.padding import InputPadder
from optstereo.models import build_from_config
from optstereo.models.upsample import ConvexUpsampler
from optstereo.training.losses import huber
from optstereo.validation import shard_samples
from pipelines.bench_labeler import _opencv
from pipelines.bench_models import THREADS, _frames, _seconds

BASE = "pretrained"
LOG_EVERY = 50
SAVE_EVERY = 200


def upsampler_inputs(model: nn.Module, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                                      tuple[int, ...]]:
    """(D_s (h, w) float32, h (C, h, w) float16, the padder's pads) that ``model``'s upsampler receives on the final
    iteration of one test-mode pass of the (H, W, 3) uint8 pair, padded as the inference engine pads it."""
    seen: dict[str, torch.Tensor] = {}

    def grab(_module: nn.Module, args: tuple[torch.Tensor, ...]) -> None:
        seen["disp"], seen["hidden"] = args[0].detach(), args[1].detach()

    left_t, right_t = to_batch(left, "cpu"), to_batch(right, "cpu")
    padder = InputPadder(left_t.shape, divis_by=8)
    left_t, right_t = padder.pad(left_t, right_t)
    handle = model.upsampler.register_forward_pre_hook(grab)
    try:
        with torch.inference_mode():
            model(left_t, right_t, test_mode=True)
    finally:
        handle.remove()
    return (seen["disp"][0, 0].float().numpy(), seen["hidden"][0].to(torch.float16).numpy(), padder.pads)


def cache(labels: Path, out: Path, base: str | Path = BASE) -> int:
    """One ``<frame>.npz`` per pair of ``labels`` (D_s, h, pads, label, confidence) from ``base``'s pass; pairs done
    are skipped; the number cached."""
    model = load_model(base).eval()
    out.mkdir(parents=True, exist_ok=True)
    done = 0
    for sample in shard_samples(labels):
        path = out / f"{sample.frame_id}.npz"
        if path.exists():
            continue
        disp, hidden, pads = upsampler_inputs(model, sample.left, sample.right)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, disp=disp, hidden=hidden, pads=np.array(pads), label=sample.label.astype(np.float32),
                 confidence=sample.confidence.astype(np.float16))
        tmp.rename(path)
        done += 1
        print(f"{sample.frame_id} {hidden.shape}", flush=True)
    return done


def unpad(full: torch.Tensor, pads: np.ndarray) -> torch.Tensor:
    """(B, 1, H', W') -> the input's (B, 1, H, W), as ``InputPadder.unpad``."""
    left, right, top, bottom = (int(p) for p in pads)
    return full[..., top: full.shape[-2] - bottom, left: full.shape[-1] - right]


def pair_loss(head: ConvexUpsampler, item: dict[str, Any]) -> torch.Tensor:
    """L_P's confidence-weighted Huber of the head's full-resolution disparity against the pair's label."""
    disp = torch.from_numpy(item["disp"])[None, None]
    hidden = torch.from_numpy(item["hidden"].astype(np.float32))[None]
    full = unpad(head(disp, hidden, None), item["pads"])[0, 0]
    label = torch.from_numpy(item["label"])
    weight = torch.from_numpy(item["confidence"].astype(np.float32))
    valid = torch.isfinite(label) & (weight > 0)
    w = weight[valid]
    return (w * huber((full[valid] - label[valid]).abs())).sum() / w.sum().clamp_min(1e-6)


@dataclasses.dataclass
class TrainState:
    """The head's training counters (saved with it)."""

    step: int = 0
    seconds: float = 0.0
    losses: list[float] = dataclasses.field(default_factory=list)


def train(cache_dir: Path, run: Path, minutes: float, lr: float = 1e-4, seed: int = 0, threads: int = 2) -> Path:
    """Fit the mask head for ``minutes`` more (resuming ``run``); returns the head's state file."""
    torch.set_num_threads(threads)
    torch.manual_seed(seed)
    files = sorted(cache_dir.glob("*.npz"))
    if not files:
        raise SystemExit(f"no cached pairs in {cache_dir}: run `cache` first")
    run.mkdir(parents=True, exist_ok=True)
    with np.load(files[0]) as first:
        head = ConvexUpsampler(int(first["hidden"].shape[0]))
    opt = torch.optim.Adam(head.parameters(), lr=lr)
    state_path, state = run / "head.pt", TrainState()
    if state_path.exists():
        saved = torch.load(state_path, weights_only=False)
        head.load_state_dict(saved["head"])
        opt.load_state_dict(saved["optimizer"])
        state = TrainState(**saved["state"])
    rng = random.Random(seed + state.step)
    end = time.monotonic() + minutes * 60
    while time.monotonic() < end:
        t0 = time.monotonic()
        with np.load(rng.choice(files)) as data:
            item = {k: data[k] for k in data.files}
        loss = pair_loss(head, item)
        opt.zero_grad()
        loss.backward()
        opt.step()
        state.step += 1
        state.seconds += time.monotonic() - t0
        state.losses.append(loss.item())
        if state.step % LOG_EVERY == 0:
            print(f"step {state.step} ({state.seconds / 60:.1f} min): loss {np.mean(state.losses[-LOG_EVERY:]):.4f}",
                  flush=True)
        if state.step % SAVE_EVERY == 0:
            _save(state_path, head, opt, state)
    _save(state_path, head, opt, state)
    return state_path


def _save(path: Path, head: nn.Module, opt: torch.optim.Optimizer, state: TrainState) -> None:
    """Atomically write the head, its optimizer and the run's counters."""
    tmp = path.with_suffix(".tmp")
    torch.save({"head": head.state_dict(), "optimizer": opt.state_dict(), "state": dataclasses.asdict(state)}, tmp)
    tmp.rename(path)


def export(run: Path, out: Path, base_spec: str | Path = BASE) -> Path:
    """``base_spec``'s weights (version 15) with the trained convex upsampler, as one safetensors file with its
    inference settings."""
    base = load_model(base_spec)
    config = dict(base.config.to_dict(), upsampler="convex")
    model = build_from_config(config)
    state = {k: v for k, v in base.state_dict().items() if not k.startswith("upsampler.")}
    head = torch.load(run / "head.pt", weights_only=False)
    state.update({f"upsampler.{k}": v for k, v in head["head"].items()})
    model.load_state_dict(state)
    model.inference_config = model_inference(base)
    return export_safetensors(out, model, step=head["state"]["step"])


def time_models(paths: dict[str, str | Path], shared: Path, repeats: int = 3) -> dict[str, dict[str, float]]:
    """Per model: median seconds per KITTI 2015 frame of ``infer`` and the median per-frame ratio to OpenCV
    SGBM-HH, all models and SGBM alternating frame by frame (2 threads, as ``make bench``)."""
    torch.set_num_threads(THREADS)
    sgbm = _opencv(cv2.STEREO_SGBM_MODE_HH)
    models = {name: load_model(path) for name, path in paths.items()}
    times: dict[str, list[float]] = {name: [] for name in [*models, "sgbm"]}
    for left, right in _frames(shared):
        times["sgbm"].append(_seconds(functools.partial(sgbm.compute, left, right), repeats))
        for name, model in models.items():
            times[name].append(_seconds(functools.partial(infer, model, left, right), repeats))
    return {name: {"s_per_frame": statistics.median(times[name]),
                   "ratio": statistics.median(m / s for m, s in zip(times[name], times["sgbm"], strict=True))}
            for name in models}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("cache")
    c.add_argument("--labels", type=Path, required=True)
    c.add_argument("--cache", type=Path, required=True)
    t = sub.add_parser("train")
    t.add_argument("--cache", type=Path, required=True)
    t.add_argument("--run", type=Path, required=True)
    t.add_argument("--minutes", type=float, default=30.0)
    t.add_argument("--lr", type=float, default=1e-4)
    m = sub.add_parser("time")
    m.add_argument("models", nargs="+", help="NAME=CHECKPOINT")
    m.add_argument("--shared", type=Path, default=Path("../shared/data"))
    m.add_argument("--out", type=Path, required=True)
    e = sub.add_parser("export")
    e.add_argument("--run", type=Path, required=True)
    e.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if args.cmd == "cache":
        print(f"{cache(args.labels, args.cache)} pairs cached")
    elif args.cmd == "train":
        print(train(args.cache, args.run, args.minutes, args.lr))
    elif args.cmd == "time":
        result = time_models(dict(m.split("=", 1) for m in args.models), args.shared)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1) + "\n")
        print(result)
    else:
        print(json.dumps(str(export(args.run, args.out))))


if __name__ == "__main__":
    main()
