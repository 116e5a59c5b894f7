"""E7 (docs/registrations.md): a student network trained end to end to reproduce a teacher network's disparity.

The teacher (any checkpoint, e.g. version 15 = ``pretrained``) runs on the very crops the student sees, after the
same augmentation (flip-swap, upscaling of small images), so its disparity is a dense target consistent with the
input by construction: no labels, no maps on disk, no GT. The student (e.g. E4's file: version 15 with both first
encoder stages separable) is trained with a sequence Huber loss (gamma 0.8, the paper's L_P weighting) against the
teacher's final full-resolution disparity on every pixel.

``maps``: the teacher's two full-frame views of every pair (``infer`` with its own settings) -> MAPS/<name>.npz.
GT is read after a run by the product: ``optstereo-eval --checkpoint F --dataset middlebury --root ../shared/data``.

``train``: -> OUT/<name>-<step>.safetensors snapshots evenly over the time budget (each a product file with the
student's own inference settings: ``optstereo-eval --checkpoint F --valset V`` scores it) and OUT/<name>.jsonl.

    python -m pipelines.studies.e2e_distill train --student e4.safetensors --teacher pretrained --pack .carry/A \
        --out OUT --device cuda --amp bf16 --batch 8 --crop 320x960 --lr 1e-4 --end-s 480 --snaps 3 --name E7a

The pack is a ``folder`` dataset written by ``pipelines.studies.gpu.distill_pack`` (``left/<id>.*``,
``right/<id>.*``).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from optstereo.api import load_model
from optstereo.checkpoint import build_model_from_checkpoint, export_safetensors, load_checkpoint
from optstereo.inference.cascade import coarse_start
from optstereo.pretrained import resolve_checkpoint_spec
from optstereo.training.distill import consistent_views, map_path, read_teacher_maps, save_teacher_map, teacher_views

GAMMA = 0.8
FINAL_LR_FRACTION = 0.8  # the last 20 % of the time budget at lr / 10
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".webp")

Pair = tuple[np.ndarray, np.ndarray]


def load_pack(root: Path) -> list[Pair]:
    """Every pair of a pack: ``root/left/<id>.*`` with ``root/right/<id>.*`` -> [(left, right)], each (H, W, 3) uint8
    RGB. Raises FileNotFoundError naming the folder when it holds no pair, ValueError naming a file that fails."""
    lefts = left_images(root)
    if not lefts:
        raise FileNotFoundError(f"{root}/left holds no image (a distill_pack folder is expected)")
    pairs = []
    for left in lefts:
        right = Path(root) / "right" / left.name
        images = [cv2.imread(str(p), cv2.IMREAD_COLOR) for p in (left, right)]
        for path, image in zip((left, right), images, strict=True):
            if image is None:
                raise ValueError(f"{path}: missing or not a readable image")
        if images[0].shape != images[1].shape:
            raise ValueError(f"{left} and {right} differ in size: {images[0].shape} vs {images[1].shape}")
        pairs.append((cv2.cvtColor(images[0], cv2.COLOR_BGR2RGB), cv2.cvtColor(images[1], cv2.COLOR_BGR2RGB)))
    return pairs


def crop_pair(pair: Pair, rng: np.random.Generator, crop: tuple[int, int], flip_swap_p: float,
              maps: Pair | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """One random (h, w) crop of a pair, both views at the same place -> (left, right, left-view target or None).

    A pair smaller than the crop is first enlarged (both views, cv2.INTER_LINEAR; ``maps`` nearest-neighbour and times
    the factor) until it covers it; with probability ``flip_swap_p`` the pair is mirrored and its views swapped (a
    valid stereo pair whose disparity is the mirrored right view's: the target is the right-view map mirrored). With
    no ``maps`` the teacher sees the result, so no target needs changing."""
    left, right = pair
    h, w = crop
    if left.shape[0] < h or left.shape[1] < w:
        f = max(h / left.shape[0], w / left.shape[1])
        size = (max(w, math.ceil(left.shape[1] * f)), max(h, math.ceil(left.shape[0] * f)))
        left, right = (cv2.resize(v, size, interpolation=cv2.INTER_LINEAR) for v in (left, right))
        if maps is not None:
            fx = size[0] / pair[0].shape[1]
            maps = tuple(cv2.resize(m, size, interpolation=cv2.INTER_NEAREST) * np.float32(fx) for m in maps)
    y = int(rng.integers(0, left.shape[0] - h + 1))
    x = int(rng.integers(0, left.shape[1] - w + 1))
    left, right = left[y:y + h, x:x + w], right[y:y + h, x:x + w]
    target = None if maps is None else maps[0][y:y + h, x:x + w]
    if rng.random() < flip_swap_p:
        left, right = right[:, ::-1], left[:, ::-1]
        target = None if maps is None else maps[1][y:y + h, x:x + w][:, ::-1]
    return (np.ascontiguousarray(left), np.ascontiguousarray(right),
            None if target is None else np.ascontiguousarray(target, dtype=np.float32))


def batch_of(pairs: list[Pair], rng: np.random.Generator, batch: int, crop: tuple[int, int],
             flip_swap_p: float = 0.5, device: torch.device | str = "cpu", maps: list[Pair] | None = None,
             ) -> tuple[torch.Tensor, ...]:
    """``batch`` random crops of random pairs -> (left, right), each (B, 3, h, w) float32 in [0, 255] on device, and
    with ``maps`` (one (left, right) pair of (H, W) float32 target views per pair, NaN = no target) the left-view
    targets (B, 1, h, w) float32 as a third tensor."""
    picks = rng.integers(0, len(pairs), batch)
    chosen = [crop_pair(pairs[int(i)], rng, crop, flip_swap_p, None if maps is None else maps[int(i)]) for i in picks]
    views = [torch.from_numpy(np.stack([c[v] for c in chosen])).permute(0, 3, 1, 2).float().to(device)
             for v in (0, 1)]
    if maps is None:
        return views[0], views[1]
    return views[0], views[1], torch.from_numpy(np.stack([c[2] for c in chosen]))[:, None].to(device)


def write_maps(teacher: str | Path, pack: Path, out: Path) -> int:
    """The teacher's two views of every pair of ``pack`` by ``infer`` with its own settings (the product's full
    pipeline: ``pretrained-accurate``'s passes, choice and filter) -> OUT/<name>.npz (resumable, atomic); pairs
    written."""
    names = pack_names(pack)
    model, written = None, 0
    for name, (left, right) in zip(names, load_pack(pack), strict=True):
        target = map_path(out, name)
        if target.is_file():
            continue
        if model is None:
            model = load_model(teacher)
        out.mkdir(parents=True, exist_ok=True)
        save_teacher_map(target, *teacher_views(model, left, right))
        written += 1
    return written


def load_maps(maps_dir: Path, pack: Path, pairs: list[Pair], every_pixel: bool = False) -> list[Pair]:
    """Each pair's teacher views kept where they agree (``optstereo.training.distill.consistent_views``, the
    labeler's 1 px rule), NaN elsewhere, or with ``every_pixel`` as they are: one (left, right) of (H, W) float32 per
    pair of ``pack``."""
    views = [read_teacher_maps(maps_dir, name, pair[0].shape[:2])
             for name, pair in zip(pack_names(pack), pairs, strict=True)]
    return views if every_pixel else [consistent_views(*v) for v in views]


def left_images(pack: Path) -> list[Path]:
    """A pack's left images (``pack/left/*`` with an image suffix), sorted: the order of every pair list here."""
    return sorted(p for p in (Path(pack) / "left").glob("*") if p.suffix.lower() in IMAGE_SUFFIXES)


def pack_names(pack: Path) -> list[str]:
    """The pair names of a pack (its left images' stems), in :func:`load_pack`'s order."""
    return [p.stem for p in left_images(pack)]


def sequence_loss(preds: list[torch.Tensor], target: torch.Tensor, gamma: float = GAMMA) -> torch.Tensor:
    """sum_k gamma^(N-1-k) * mean Huber(pred_k - target) (delta 1 px) over the target's finite pixels: preds N x
    (B, 1, H, W), target (B, 1, H, W) float32 (detached, NaN = none) -> a scalar."""
    n, valid = len(preds), torch.isfinite(target)
    if bool(valid.all()):
        return sum(gamma ** (n - 1 - k) * F.smooth_l1_loss(p.float(), target, beta=1.0) for k, p in enumerate(preds))
    goal = target[valid]
    return sum(gamma ** (n - 1 - k) * F.smooth_l1_loss(p.float()[valid], goal, beta=1.0) for k, p in enumerate(preds))


def scaled_to_eight(size: tuple[int, int], scale: float) -> tuple[int, int]:
    """(h, w) times ``scale``, each side rounded to the nearest multiple of 8 (at least 8)."""
    return tuple(max(8, round(v * scale / 8) * 8) for v in size)  # type: ignore[return-value]


@torch.no_grad()
def teacher_target(teacher: nn.Module, left: torch.Tensor, right: torch.Tensor, scale: float = 1.0,
                   coarse: bool = False) -> torch.Tensor:
    """The teacher's final full-resolution disparity (B, 1, H, W) float32 of (B, 3, H, W) crops (H, W multiples of
    8), in float32 at its own N_s: with ``scale`` != 1 the crops are resized bilinearly to :func:`scaled_to_eight`
    and the disparity brought back to (H, W) and times W / w' (the product's pass at a scale, in tensors); with
    ``coarse`` the GRU starts from ``optstereo.inference.cascade.coarse_start`` (a half-size pass)."""
    h, w = left.shape[-2:]
    if scale != 1.0:
        size = scaled_to_eight((h, w), scale)
        left, right = (F.interpolate(v, size=size, mode="bilinear", align_corners=False) for v in (left, right))
    start = {"disp_init": coarse_start(teacher, left, right, None)} if coarse else {}
    _, full = teacher(left, right, test_mode=True, **start)
    full = full.float()
    if full.shape[-2:] != (h, w):
        full = F.interpolate(full, size=(h, w), mode="bilinear", align_corners=False) * (w / full.shape[-1])
    return full


def load_student(spec: str | Path, device: torch.device) -> nn.Module:
    """A checkpoint (path or registry name) as a trainable model on device, its inference settings kept."""
    model = build_model_from_checkpoint(load_checkpoint(resolve_checkpoint_spec(spec)), device=device)
    return model.train()


def load_teacher(spec: str | Path, device: torch.device) -> nn.Module:
    """A checkpoint as a frozen model in eval mode on device (the plain network, not the engineered CPU pass)."""
    model = build_model_from_checkpoint(load_checkpoint(resolve_checkpoint_spec(spec)), device=device)
    for p in model.parameters():
        p.requires_grad_(False)
    return model.eval()


def snapshot_times(end_s: float, snaps: int) -> list[float]:
    """Seconds after the start at which the ``snaps`` snapshots are written: evenly, the last at ``end_s``."""
    return [end_s * (i + 1) / snaps for i in range(snaps)]


def train(student: str | Path, teacher: str | Path, pack: Path, out: Path, *, name: str = "E7",
          device: str = "cuda", amp: str = "bf16", batch: int = 8, crop: tuple[int, int] = (320, 960),
          lr: float = 1e-4, end_s: float = 480.0, snaps: int = 3, seed: int = 0, steps_max: int | None = None,
          flip_swap_p: float = 0.5, teacher_scale: float = 1.0, teacher_coarse: bool = False,
          maps: Path | None = None, every_pixel: bool = False) -> list[Path]:
    """Train ``student`` to reproduce ``teacher`` on crops of ``pack`` for ``end_s`` seconds (or ``steps_max``
    steps, whichever comes first) -> the snapshot files written (the last always at the end). With ``maps``
    (:func:`write_maps`' folder) the targets are the teacher's consistent full-frame views, cropped with the pair,
    and ``teacher`` is not run; with ``every_pixel`` also where the views disagree."""
    dev = torch.device(device)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    out.mkdir(parents=True, exist_ok=True)
    pairs = load_pack(pack)
    targets = None if maps is None else load_maps(maps, pack, pairs, every_pixel)
    model = load_student(student, dev)
    ref = load_teacher(teacher, dev) if targets is None else None
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    autocast = torch.autocast(dev.type, dtype=torch.bfloat16, enabled=amp == "bf16")
    due, written, step, t0 = snapshot_times(end_s, snaps), [], 0, time.monotonic()
    with open(out / f"{name}.jsonl", "a") as log:
        while True:
            elapsed = time.monotonic() - t0
            done = elapsed >= end_s or (steps_max is not None and step >= steps_max)
            if done or (due and elapsed >= due[0]):
                due = due[1:]
                written.append(export_safetensors(out / f"{name}-{step}.safetensors", model, step=step))
                if done:
                    return written
            for group in opt.param_groups:
                group["lr"] = lr if elapsed < FINAL_LR_FRACTION * end_s else lr / 10
            if targets is None:
                left, right = batch_of(pairs, rng, batch, crop, flip_swap_p, dev)
                target = teacher_target(ref, left, right, teacher_scale, teacher_coarse)
            else:
                left, right, target = batch_of(pairs, rng, batch, crop, flip_swap_p, dev, targets)
            with autocast:
                preds = model(left, right)
            loss = sequence_loss(preds, target)
            if not torch.isfinite(loss):
                raise FloatingPointError(f"non-finite loss at step {step}")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            opt.step()
            step += 1
            if step % 25 == 0 or step == 1:
                epe = (preds[-1].detach().float() - target).abs().nanmean().item()
                log.write(json.dumps({"step": step, "s": round(time.monotonic() - t0, 1), "loss": loss.item(),
                                      "epe_to_teacher": epe, "lr": opt.param_groups[0]["lr"]}) + "\n")
                log.flush()


def _crop(text: str) -> tuple[int, int]:
    h, w = (int(v) for v in text.lower().split("x"))
    if h % 8 or w % 8:
        raise argparse.ArgumentTypeError(f"crop {text}: both sides must be multiples of 8")
    return h, w


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    sub = parser.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train")
    t.add_argument("--student", required=True)
    t.add_argument("--teacher", default="pretrained")
    t.add_argument("--pack", type=Path, required=True)
    t.add_argument("--out", type=Path, required=True)
    t.add_argument("--name", default="E7")
    t.add_argument("--device", default="cuda")
    t.add_argument("--amp", choices=("none", "bf16"), default="bf16")
    t.add_argument("--batch", type=int, default=8)
    t.add_argument("--crop", type=_crop, default=(320, 960))
    t.add_argument("--lr", type=float, default=1e-4)
    t.add_argument("--end-s", type=float, default=480.0)
    t.add_argument("--snaps", type=int, default=3)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--steps-max", type=int, default=None)
    t.add_argument("--teacher-scale", type=float, default=1.0, help="the teacher's input scale (version 14: 1.625)")
    t.add_argument("--teacher-coarse", action="store_true", help="the teacher's GRU starts from a half-size pass")
    t.add_argument("--maps", type=Path, default=None, help="targets: the teacher's views written by `maps`")
    t.add_argument("--every-pixel", action="store_true", help="--maps: also where the teacher's views disagree")
    t.add_argument("--threads", type=int, default=None)
    m = sub.add_parser("maps", help="the teacher's two full-frame views of every pair of a pack (resumable)")
    m.add_argument("--teacher", default="pretrained-accurate")
    m.add_argument("--pack", type=Path, required=True)
    m.add_argument("--out", type=Path, required=True)
    a = parser.parse_args(argv)
    if a.cmd == "maps":
        print(f"{write_maps(a.teacher, a.pack, a.out)} pairs written to {a.out}")
        return
    if a.threads:
        torch.set_num_threads(a.threads)
    files = train(a.student, a.teacher, a.pack, a.out, name=a.name, device=a.device, amp=a.amp, batch=a.batch,
                  crop=a.crop, lr=a.lr, end_s=a.end_s, snaps=a.snaps, seed=a.seed, steps_max=a.steps_max,
                  teacher_scale=a.teacher_scale, teacher_coarse=a.teacher_coarse, maps=a.maps,
                  every_pixel=a.every_pixel)
    print("\n".join(str(f) for f in files))


if __name__ == "__main__":
    main()
