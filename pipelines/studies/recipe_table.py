"""Issue 49, part 3: training recipes for the same CPU budget -> steps/s and GT-free validation error.

Every recipe starts from the same ``--init`` and trains for the same wall-clock budget (``--max-minutes``) with the
settings of pipelines/studies/recipes/cpu_main.yaml, ``--lambda-t 0 --conf-weight``, the same seed and a constant
learning rate (``--schedule constant --lr LR``: a OneCycle schedule sized in steps would be cut at a different point
by the time cap of each recipe, so the recipes would differ in their schedule as well as in their speed). Each result
is scored on a GT-free validation set (``optstereo-eval --valset``); row 0 is the init's own score.

Recipes (one change each against ``whole``):

    whole        the whole network (the trainer's CPU recipe: its crop and N_s)
    frozen       the feature encoder fixed, no backward through it (``OptStereo.freeze_encoder``; the trainer has no
                 flag for it since this table chose ``whole``: the study runs the trainer with the model frozen)
    cached       the encoder's features of ONE fixed crop per training pair (bottom rows, centred) precomputed into
                 OUT/cached/cache/*.npz, then the rest (correlation, GRU, upsampler) trained on them with the same
                 losses (L_P confidence-weighted, L_R, L_S); no augmentation is possible (the features belong to the
                 crop). The cache's build time is reported apart and not charged to the budget.
    small_crop   crops of half the area (same aspect, sides rounded to multiples of 8)
    fewer_iters  N_s halved
    bf16         --amp bf16; run only where the CPU has native bf16 (AVX512-BF16/AMX), else a row says why not

Resumable: a recipe whose RUN/model.safetensors and RUN/val/gtfree.json exist is skipped; a run that was cut off
is started again from scratch (resuming would give it more than the budget). Results: OUT/table.md, OUT/table.json.

    python -m pipelines.studies.recipe_table --labels out/labels/kitti_unlabelled_k03 --valset /work/valset \
        --init pretrained --minutes 60 --out results/recipes
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

#: The checkout holding this script: the trainer and the evaluator run from it (``python -m optstereo.cli``), not
#: from whatever checkout the environment's console scripts were installed from (a git worktree shares one .venv).
REPO = Path(__file__).resolve().parents[2]
TRAIN = [sys.executable, "-m", "optstereo.cli", "train"]
#: The trainer with OptStereo's encoder frozen before the optimiser is built (``python -m ... train-frozen FLAGS``).
TRAIN_FROZEN = [sys.executable, "-m", "pipelines.studies.recipe_table", "train-frozen"]
EVAL = [sys.executable, "-m", "optstereo.cli", "eval"]
RECIPE = Path(__file__).resolve().parent / "recipes" / "cpu_main.yaml"
RECIPES = ("whole", "frozen", "cached", "small_crop", "fewer_iters", "bf16")
#: So many steps that the time cap ends every run (and its only checkpoint is the final one).
NO_STEP_CAP = 10**9


# -- the recipes as trainer flags ----------------------------------------------------------------------------------
def half_area(crop: tuple[int, int]) -> tuple[int, int]:
    """(H, W) with about half the area of ``crop`` and the same aspect, sides multiples of 8."""
    return tuple(max(8, round(side / math.sqrt(2) / 8) * 8) for side in crop)  # type: ignore[return-value]


def base_flags(args: argparse.Namespace) -> list[str]:
    """The settings every recipe shares (cpu_main.yaml, no L_T, confidence-weighted L_P, constant LR, time cap)."""
    return ["--config", str(RECIPE), "--labels", str(args.labels), "--init", str(args.init), "--lambda-t", "0",
            "--conf-weight", "--schedule", "constant", "--lr", str(args.lr), "--steps", str(NO_STEP_CAP),
            "--ckpt-every", str(NO_STEP_CAP), "--max-minutes", str(args.minutes), "--threads", str(args.threads),
            "--seed", str(args.seed), "--quiet"]


def recipe_flags(name: str) -> list[str]:
    """The one change of recipe ``name`` against ``whole`` (the cached recipe starts from ``frozen``'s config)."""
    from optstereo.training.config import TrainConfig

    recipe = TrainConfig.load(RECIPE)
    crop = half_area(recipe.data.crop)
    return {"whole": [], "frozen": [], "cached": [],
            "small_crop": ["--crop", f"{crop[0]}x{crop[1]}"], "fewer_iters": ["--iters", str(recipe.model.iters // 2)],
            "bf16": ["--amp", "bf16"]}[name]


def _env(threads: int) -> dict[str, str]:
    path = os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)
    return {**os.environ, "PYTHONPATH": path, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}


def _run(cmd: list[str], threads: int) -> None:
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, env=_env(threads))


# -- the cached-features recipe ------------------------------------------------------------------------------------
def fixed_crop(shape: tuple[int, int], crop: tuple[int, int]) -> tuple[slice, slice]:
    """The cache's one crop of a frame: the bottom rows, centred, at most the frame (multiples of 8)."""
    h, w = min(crop[0], shape[0] // 8 * 8), min(crop[1], shape[1] // 8 * 8)
    x0 = (shape[1] - w) // 2
    return slice(shape[0] - h, shape[0]), slice(x0, x0 + w)


def build_cache(model: Any, cfg: Any, cache: Path) -> float:
    """One npz per training pair: the fixed crop's left/right (3, h, w) float32, label/valid/weight (1, h, w) and the
    frozen encoder's [F_l; F_r] (2, C, h/8, w/8) float32; existing files are kept. Returns the seconds it took."""
    import torch

    from optstereo.data.transforms import to_tensors
    from optstereo.models.optstereo import normalize_image
    from optstereo.validation import shard_samples

    cache.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    model.eval()
    for sample in shard_samples(cfg.data.labels):
        path = cache / f"{sample.frame_id.replace('/', '_')}.npz"
        if path.exists():
            continue
        rows, cols = fixed_crop(sample.left.shape[:2], cfg.data.crop)
        left, right, label, valid = to_tensors(sample.left[rows, cols], sample.right[rows, cols],
                                               sample.label[rows, cols], cfg.data.max_label_disp)
        weight = np.nan_to_num(sample.confidence[rows, cols].astype(np.float32))[None]
        with torch.no_grad():
            feats = model.feature_encoder(normalize_image(torch.stack([left, right])))
        tmp = path.with_suffix(".tmp.npz")
        # The views as uint8 (their values are integers in [0, 255]): a third of the cache's size.
        np.savez(tmp, left=left.numpy().astype(np.uint8), right=right.numpy().astype(np.uint8), label=label.numpy(),
                 valid=valid.numpy(),
                 weight=weight, feats=feats.numpy())
        os.replace(tmp, path)
    return time.perf_counter() - start


def _batch(files: list[Path]) -> dict[str, Any]:
    import torch

    loaded = [np.load(f) for f in files]
    out = {k: torch.from_numpy(np.stack([d[k] for d in loaded])) for k in ("left", "right", "label", "valid", "weight")}
    out["left"], out["right"] = out["left"].float(), out["right"].float()
    feats = torch.from_numpy(np.stack([d["feats"] for d in loaded]))  # (B, 2, C, h, w) -> [F_l of all; F_r of all]
    out["feats"] = torch.cat([feats[:, 0], feats[:, 1]])
    return out


def train_cached(run_dir: Path, flags: list[str], threads: int) -> None:
    """The cached recipe: the frozen recipe's resolved config, the cache, then Adam on the trainable parts for
    ``max_minutes`` over the cached crops (seeded shuffles); RUN/model.safetensors and RUN/summary.json as the
    trainer writes them."""
    import torch
    import yaml

    from optstereo.checkpoint import export_safetensors
    from optstereo.training import loop
    from optstereo.training.checkpoints import init_weights
    from optstereo.training.config import TrainConfig

    printed = subprocess.run([*TRAIN, *flags, "--out", str(run_dir), "--print-config"],
                             check=True, capture_output=True, text=True, env=_env(threads)).stdout
    cfg = TrainConfig.from_dict(yaml.safe_load(printed))
    torch.set_num_threads(threads)
    torch.manual_seed(cfg.seed)
    model = loop.build_model(cfg)
    init_weights(model, cfg.init)
    model.freeze_encoder()
    cache_seconds = build_cache(model, cfg, run_dir / "cache")
    files = sorted((run_dir / "cache").glob("*.npz"))
    optimizer, _ = loop.build_optimizer(model, cfg)
    loss_fn = loop.build_loss(cfg)
    rng = np.random.default_rng(cfg.seed)
    bs, order, step, start = cfg.data.batch_size, [], 0, time.perf_counter()
    model.train()
    while time.perf_counter() - start < 60 * cfg.max_minutes or step == 0:
        if len(order) < bs:
            order += list(rng.permutation(len(files)))
        batch = _batch([files[i] for i in order[:bs]])
        order = order[bs:]
        preds = model(batch["left"], batch["right"], iters=cfg.model.iters, features=batch["feats"])
        total, _ = loss_fn(preds, batch["left"], batch["right"], batch["label"], batch["valid"], batch["weight"])
        optimizer.zero_grad(set_to_none=True)
        total.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.optim.clip_grad if cfg.optim.clip_grad > 0 else math.inf)
        optimizer.step()
        step += 1
    seconds = time.perf_counter() - start
    export_safetensors(run_dir / "model.safetensors", model, step=step)
    summary = {"start_step": 0, "step": step, "seconds": seconds, "cache_seconds": cache_seconds,
               "cached_pairs": len(files)}
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))


# -- running and scoring -------------------------------------------------------------------------------------------
def score(checkpoint: str | Path, valset: Path, out: Path, threads: int) -> dict[str, float]:
    """optstereo-eval --valset (OUT/gtfree.json, reused when present) -> its pooled summary."""
    report = out / "gtfree.json"
    if not report.is_file():
        _run([*EVAL, "--valset", str(valset), "--checkpoint", str(checkpoint), "--out", str(out),
              "--quiet"], threads)
    return json.loads(report.read_text())["summary"]


def run_recipe(name: str, args: argparse.Namespace) -> dict[str, Any]:
    """Train (unless done) and score one recipe; its table row."""
    from optstereo.inference.engine import cpu_has_native_bf16

    run_dir = args.out / name
    if name == "bf16" and not cpu_has_native_bf16():
        return {"recipe": name, "note": "not run: bf16 is not native on this CPU (AVX2 only: emulated, slower than "
                                        "float32)"}
    model = run_dir / "model.safetensors"
    if not model.is_file():  # a finished run is only (re-)scored
        if run_dir.exists():
            shutil.rmtree(run_dir)  # cut off: start again, a resumed run would get more than the budget
        flags = [*base_flags(args), *recipe_flags(name)]
        if name == "cached":
            train_cached(run_dir, flags, args.threads)
        else:
            _run([*(TRAIN_FROZEN if name == "frozen" else TRAIN), *flags, "--out", str(run_dir)], args.threads)
    scores = score(model, args.valset, run_dir / "val", args.threads)
    summary = json.loads((run_dir / "summary.json").read_text())
    from optstereo.training.config import TrainConfig

    batch = TrainConfig.load(RECIPE).data.batch_size
    steps = summary["step"] - summary["start_step"]
    change = {"cached": "fixed crops, cached encoder features", "frozen": "encoder frozen"}.get(
        name, " ".join(recipe_flags(name)))
    row = {"recipe": name, "flags": change or "(the recipe)", "steps": steps, "seconds": summary["seconds"],
           "steps_per_s": steps / summary["seconds"], "samples_per_s": steps * batch / summary["seconds"], **scores}
    if "cache_seconds" in summary:
        row["note"] = f"cache of {summary['cached_pairs']} fixed crops built in {summary['cache_seconds']:.0f} s"
    return row


def table_md(rows: list[dict[str, Any]], args: argparse.Namespace) -> str:
    def num(row: dict[str, Any], key: str, fmt: str) -> str:
        value = row.get(key)
        return "" if value is None else format(value, fmt)

    lines = [f"# Training recipes for the same CPU budget ({args.minutes:g} min, {args.threads} threads)", "",
             f"From `{args.init}`, cpu_main.yaml with `--lambda-t 0 --conf-weight --schedule constant --lr {args.lr}`, "
             f"seed {args.seed}; scored on `{args.valset}` (optstereo-eval --valset) at the init's inference N_s "
             "(a recipe's training N_s does not change it).", "",
             "| recipe | change | steps | steps/s | samples/s | PVM EPE (px) | PVM bad-3 (%) | photometric | note |",
             "|---|---|---:|---:|---:|---:|---:|---:|---|"]
    for row in rows:
        lines.append(f"| {row['recipe']} | {row.get('flags', '')} | {num(row, 'steps', 'd')} | "
                     f"{num(row, 'steps_per_s', '.3f')} | {num(row, 'samples_per_s', '.3f')} | "
                     f"{num(row, 'pvm_epe', '.3f')} | {num(row, 'pvm_bad3', '.2f')} | "
                     f"{num(row, 'photometric', '.4f')} | {row.get('note', '')} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--labels", type=Path, required=True, help="PVM shard directory to train on")
    parser.add_argument("--valset", type=Path, required=True, help="GT-free validation set (optstereo-distill valset)")
    parser.add_argument("--init", default="pretrained", help="start checkpoint of every recipe")
    parser.add_argument("--minutes", type=float, required=True, help="wall-clock training budget per recipe")
    parser.add_argument("--out", type=Path, default=Path("results/recipes"))
    parser.add_argument("--recipes", default=",".join(RECIPES), help=f"comma-separated subset of {RECIPES}")
    parser.add_argument("--lr", type=float, default=1e-4, help="constant learning rate of every recipe")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    names = [n for n in args.recipes.split(",") if n]
    unknown = sorted(set(names) - set(RECIPES))
    if unknown:
        parser.error(f"unknown recipes {unknown}; choose from {RECIPES}")
    args.out.mkdir(parents=True, exist_ok=True)
    rows = [{"recipe": "init", "flags": "(no training)", **score(args.init, args.valset, args.out / "init" / "val",
                                                                 args.threads)}]
    rows += [run_recipe(name, args) for name in names]
    (args.out / "table.json").write_text(json.dumps({"minutes": args.minutes, "threads": args.threads,
                                                     "init": str(args.init), "lr": args.lr, "rows": rows}, indent=2))
    (args.out / "table.md").write_text(table_md(rows, args))
    print(table_md(rows, args))
    return rows


def train_frozen(argv: list[str]) -> None:
    """``optstereo-train ARGV`` with every OptStereo the trainer builds frozen (``OptStereo.freeze_encoder``), before
    its weights are loaded and its optimiser (which takes the trainable parameters only) is built."""
    from optstereo.cli.train import train_main
    from optstereo.training import loop

    build = loop.build_model
    loop.build_model = lambda cfg: build(cfg).freeze_encoder()
    train_main.main(args=argv, prog_name="optstereo-train (encoder frozen)")


if __name__ == "__main__":
    if sys.argv[1:2] == ["train-frozen"]:
        train_frozen(sys.argv[2:])
    else:
        main()
