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
    python -m pipelines.studies.convex_head train-hybrid --cache DIR --labels SHARDS --run RUN2 --minutes 10
    python -m pipelines.studies.convex_head score-hybrid --state RUN2/hybrid.pt --valset VAL --out DIR
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import random
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from optstereo.api import load_model
from optstereo.checkpoint import export_safetensors, model_inference
from optstereo.inference.engine import to_batch
from optstereo.inference.padding import InputPadder
from optstereo.models import build_from_config
from optstereo.models.optstereo import normalize_image
from optstereo.models.upsample import ConvexUpsampler
from optstereo.training.losses import huber
from optstereo.validation import open_valset, score, shard_samples, write_report
from pipelines.bench_models import THREADS

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
        tmp = out / f"{sample.frame_id}.partial.npz"  # ends in .npz: np.savez keeps the name
        np.savez(tmp, disp=disp, hidden=hidden, pads=np.array(pads), label=sample.label.astype(np.float32),
                 confidence=sample.confidence.astype(np.float16))
        tmp.rename(path)
        done += 1
        print(f"{sample.frame_id} {hidden.shape}", flush=True)
    return done


def cached(cache_dir: Path) -> list[Path]:
    """The complete pairs of a cache (a file an interrupted ``cache`` left half-written ends in .partial.npz)."""
    return sorted(p for p in cache_dir.glob("*.npz") if not p.name.endswith(".partial.npz"))


def unpad(full: torch.Tensor, pads: np.ndarray) -> torch.Tensor:
    """(B, 1, H', W') -> the input's (B, 1, H, W), as ``InputPadder.unpad``."""
    left, right, top, bottom = (int(p) for p in pads)
    return full[..., top: full.shape[-2] - bottom, left: full.shape[-1] - right]


def pair_loss(head: ConvexUpsampler, item: dict[str, Any]) -> torch.Tensor:
    """L_P's confidence-weighted Huber of the head's full-resolution disparity against the pair's label."""
    disp = torch.from_numpy(item["disp"])[None, None]
    hidden = torch.from_numpy(item["hidden"].astype(np.float32))[None]
    return weighted_huber(unpad(head(disp, hidden, None), item["pads"])[0, 0], item)


def weighted_huber(full: torch.Tensor, item: dict[str, Any]) -> torch.Tensor:
    """L_P's confidence-weighted Huber of an (H, W) disparity against a cached pair's label."""
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
    files = cached(cache_dir)
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


def bilinear_logits(factor: int = 8) -> torch.Tensor:
    """(9 * f * f,) mask logits (before ConvexUpsampler's 0.25 scale) whose softmax over the 3x3 coarse neighbours are
    the weights of bilinear upsampling (align_corners=False), in the mask's (neighbour, sub-row, sub-column) order."""
    weights = np.zeros((3, 3, factor, factor))

    def taps(i: int) -> dict[int, float]:
        d = (i + 0.5) / factor - 0.5  # the sub-pixel's offset from its coarse pixel's centre, in coarse pixels
        return {0: -d, 1: 1 + d} if d < 0 else {1: 1 - d, 2: d}

    for i in range(factor):
        for j in range(factor):
            for ky, wy in taps(i).items():
                for kx, wx in taps(j).items():
                    weights[ky, kx, i, j] = wy * wx
    return torch.from_numpy(4 * np.log(weights.reshape(-1) + 1e-12)).float()


class HybridUpsampler(nn.Module):
    """U2: the paper's upsampler with its bilinear step replaced by a convex combination of the 3x3 coarse
    neighbours (replicate-padded) from a mask head on h: D = U + conv2(ReLU(conv1([U / f, I_l]))).

    Built from a trained ``ConvUpsampler`` (its two convolutions, shared) with the mask's last layer zero and its
    biases at :func:`bilinear_logits`, so that it starts as that upsampler exactly.
    Shapes: disp_low (B, 1, h, w), hidden (B, C, h, w), image (B, 3, f h, f w) in [-1, 1] -> (B, 1, f h, f w).
    """

    def __init__(self, conv: nn.Module, hidden_dim: int, factor: int = 8) -> None:
        super().__init__()
        self.convex = ConvexUpsampler(hidden_dim, factor)
        last = self.convex.mask[2]
        nn.init.zeros_(last.weight)
        with torch.no_grad():
            last.bias.copy_(bilinear_logits(factor))
        self.conv = conv
        self.factor = factor

    def coarse(self, disp_low: torch.Tensor, hidden: torch.Tensor) -> torch.Tensor:
        """U: the convex combination, (B, 1, f h, f w)."""
        b, _, h, w = disp_low.shape
        f = self.factor
        mask = (0.25 * self.convex.mask(hidden)).float().view(b, 1, 9, f, f, h, w).softmax(dim=2)
        padded = torch.nn.functional.pad(f * disp_low, (1, 1, 1, 1), mode="replicate")
        neigh = torch.nn.functional.unfold(padded, kernel_size=3).view(b, 1, 9, 1, 1, h, w)
        return (mask * neigh).sum(dim=2).permute(0, 1, 4, 2, 5, 3).reshape(b, 1, f * h, f * w)

    def forward(self, disp_low: torch.Tensor, hidden: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        up = self.coarse(disp_low, hidden)
        x = torch.cat([up / self.factor, image.to(up.dtype)], dim=1)
        return up + self.conv.conv2(self.conv.relu(self.conv.conv1(x)))


def hybrid_model(base_spec: str | Path = BASE, state: Path | None = None) -> nn.Module:
    """``base_spec`` (version 15) with a :class:`HybridUpsampler` built on its upsampler (loaded from ``state``, a
    ``train-hybrid`` run's ``hybrid.pt``, when given): the model object the validation set scores."""
    model = load_model(base_spec)
    hybrid = HybridUpsampler(copy.deepcopy(model.upsampler), model.config.hidden_dim)
    if state is not None:
        hybrid.load_state_dict(torch.load(state, weights_only=True))
    model.upsampler = hybrid
    return model


def train_hybrid(cache_dir: Path, labels: Path, run: Path, minutes: float, lr: float = 1e-4, seed: int = 0,
                 holdout_every: int = 10) -> Path:
    """U2: fit a :class:`HybridUpsampler` (both parts) on the cached pairs but every ``holdout_every``-th (their mean
    loss is printed at the start and every LOG_EVERY * 10 steps); returns ``run/hybrid.pt``."""
    torch.set_num_threads(THREADS)
    torch.manual_seed(seed)
    hybrid = hybrid_model().upsampler
    files = cached(cache_dir)
    held = {f.stem for f in files[::holdout_every]}
    images = {s.frame_id: s.left for s in shard_samples(labels)}

    def loss_of(stem: str) -> torch.Tensor:
        with np.load(cache_dir / f"{stem}.npz") as data:
            item = {k: data[k] for k in data.files}
        pads = tuple(int(p) for p in item["pads"])
        image = torch.from_numpy(images[stem]).permute(2, 0, 1)[None].float()
        image = normalize_image(torch.nn.functional.pad(image, pads, mode="replicate"))
        full = unpad(hybrid(torch.from_numpy(item["disp"])[None, None],
                            torch.from_numpy(item["hidden"].astype(np.float32))[None], image), item["pads"])[0, 0]
        return weighted_huber(full, item)

    def held_loss() -> float:
        with torch.no_grad():
            return float(np.mean([loss_of(stem).item() for stem in sorted(held)]))

    print(f"held-out loss at the start: {held_loss():.4f}", flush=True)
    opt = torch.optim.Adam(hybrid.parameters(), lr=lr)
    train_ids = [f.stem for f in files if f.stem not in held]
    rng, end, step = random.Random(seed), time.monotonic() + 60 * minutes, 0
    while time.monotonic() < end:
        loss = loss_of(rng.choice(train_ids))
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        if step % (LOG_EVERY * 10) == 0:
            print(f"step {step}: held-out loss {held_loss():.4f}", flush=True)
    print(f"step {step}: held-out loss {held_loss():.4f}", flush=True)
    run.mkdir(parents=True, exist_ok=True)
    torch.save(hybrid.state_dict(), run / "hybrid.pt")
    return run / "hybrid.pt"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    sub = parser.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("cache")
    c.add_argument("--labels", type=Path, required=True)
    c.add_argument("--cache", type=Path, required=True)
    t = sub.add_parser("train")
    t.add_argument("--cache", type=Path, required=True)
    t.add_argument("--run", type=Path, required=True)
    t.add_argument("--minutes", type=float, default=30.0)
    t.add_argument("--lr", type=float, default=1e-4)
    h = sub.add_parser("train-hybrid", help="U2: the hybrid upsampler, both parts")
    h.add_argument("--cache", type=Path, required=True)
    h.add_argument("--labels", type=Path, required=True, help="the shards the cache came from (their left images)")
    h.add_argument("--run", type=Path, required=True)
    h.add_argument("--minutes", type=float, default=10.0)
    v = sub.add_parser("score-hybrid", help="U2 on a validation set -> OUT/gtfree.json")
    v.add_argument("--state", type=Path, required=True)
    v.add_argument("--valset", type=Path, required=True)
    v.add_argument("--out", type=Path, required=True)
    e = sub.add_parser("export")
    e.add_argument("--run", type=Path, required=True)
    e.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if args.cmd == "cache":
        print(f"{cache(args.labels, args.cache)} pairs cached")
    elif args.cmd == "train":
        print(train(args.cache, args.run, args.minutes, args.lr))
    elif args.cmd == "train-hybrid":
        print(train_hybrid(args.cache, args.labels, args.run, args.minutes))
    elif args.cmd == "score-hybrid":
        torch.set_num_threads(THREADS)
        result = score(hybrid_model(state=args.state), open_valset(args.valset), progress=True, what="U2")
        write_report(result, args.out, f"version 15 + {args.state}", args.valset)
        print(result.summary)
    else:
        print(json.dumps(str(export(args.run, args.out))))


if __name__ == "__main__":
    main()
