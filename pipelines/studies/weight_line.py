"""W1 (issue 49, docs/registrations.md): version 15's weights moved along the straight line from version 14.

    python -m pipelines.studies.weight_line --out /work/w1 [--alphas 0.5 0.75 1.25 1.5 2.0]

Writes OUT/w<a>.safetensors = theta_14 + a (theta_15 - theta_14) with version 15's inference settings (float32: no
int8 clips beside them), then scores each (and version 15 itself, a = 1) on the GT-free validation set with
``optstereo-eval --valset`` (OPTSTEREO_INT8=0) into OUT/w<a>.val/gtfree.json, resumable: a scored arm is skipped.
Judge with ``python -m pipelines.studies.long_run compare OUT/w1.val/gtfree.json OUT/w<a>.val/gtfree.json``.

W2 (docs/registrations.md): the uniform average of a training run's checkpoints, version 15's inference settings:

    python -m pipelines.studies.weight_line average --out W2.safetensors RUN/ckpt-*.pt
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import torch

from optstereo.api import load_model
from optstereo.checkpoint import average_checkpoints, export_safetensors, model_inference


def on_line(start: dict[str, torch.Tensor], end: dict[str, torch.Tensor], alpha: float) -> dict[str, torch.Tensor]:
    """``start + alpha (end - start)`` per tensor (float tensors; others taken from ``end``).

    Args:
        start, end: state dicts with the same keys and shapes (version 14's and version 15's).
        alpha: 0 gives ``start``, 1 gives ``end``; > 1 extrapolates past ``end``.
    """
    if start.keys() != end.keys():
        raise ValueError(f"the two state dicts differ in keys: {sorted(start.keys() ^ end.keys())[:5]}")
    out = {}
    for key, b in end.items():
        a = start[key]
        if a.shape != b.shape:
            raise ValueError(f"{key}: shapes {tuple(a.shape)} and {tuple(b.shape)} differ")
        out[key] = a + alpha * (b - a) if b.is_floating_point() else b.clone()
    return out


def average_file(checkpoints: list[Path], out: Path) -> Path:
    """Write the average of ``checkpoints``' weights (``optstereo.checkpoint.average_checkpoints``) to ``out`` with
    version 15's inference settings."""
    model = load_model("pretrained")
    model.load_state_dict(average_checkpoints(checkpoints).model_state)
    return export_safetensors(out, model, inference=model_inference(model))


def arm_file(out: Path, alpha: float) -> Path:
    """Write (once) OUT/w<alpha>.safetensors: the weights at ``alpha`` with version 15's inference settings."""
    path = out / f"w{alpha:g}.safetensors"
    if not path.exists():
        end = load_model("pretrained")
        start = load_model("pretrained-accurate").state_dict()
        end.load_state_dict(on_line(start, end.state_dict(), alpha))
        export_safetensors(path, end, inference=model_inference(end))
    return path


def score(checkpoint: Path, valset: Path, out: Path) -> None:
    """Score ``checkpoint`` on the validation set in float32 into the folder ``out`` (skipped when scored)."""
    if (out / "gtfree.json").exists():
        return
    env = dict(os.environ, OPTSTEREO_INT8="0")
    cmd = [sys.executable, "-m", "optstereo.cli", "eval", "--checkpoint", str(checkpoint), "--valset", str(valset),
           "--out", str(out), "--threads", "2"]
    subprocess.run(cmd, check=True, env=env)


def main(argv: list[str] | None = None) -> None:
    if argv is None:
        argv = sys.argv[1:]
    if argv[:1] == ["average"]:
        avg = argparse.ArgumentParser(prog="weight_line average")
        avg.add_argument("--out", type=Path, required=True)
        avg.add_argument("checkpoints", type=Path, nargs="+")
        a = avg.parse_args(argv[1:])
        print(average_file(sorted(a.checkpoints), a.out))
        return
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--valset", type=Path, default=Path("/work/valset"))
    parser.add_argument("--alphas", type=float, nargs="+", default=[1.0, 0.5, 0.75, 1.25, 1.5, 2.0])
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for alpha in args.alphas:
        score(arm_file(args.out, alpha), args.valset, args.out / f"w{alpha:g}.val")


if __name__ == "__main__":
    main()
