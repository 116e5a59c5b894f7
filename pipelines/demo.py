"""`make demo`: the whole PVStereo loop on the embedded `sample` dataset, on CPU, in a few minutes.

Steps (each is the real command line a user would type; they are printed before they run):
1. ``pvm-label``: PVM pseudo-labels for the sample (scikit-image's Middlebury motorcycle + synthetic scenes);
2. ``optstereo-train``: self-supervised training from those shards (time-boxed);
3. ``optstereo-eval``: the network and, with the same ruler, the labels on the sample's ground truth;
4. ``optstereo-predict``: disparity files for the motorcycle pair, plus an overview picture;
5. the two shipped models (``--checkpoint pretrained``, one pass, and ``pretrained-accurate``, three; trained on
   unlabelled driving pairs only) on the same pair and GT.

Model size: the paper-size OptStereo (C = 256) takes tens of seconds per 320x736 training step on this 2-core CPU,
so a few minutes would be only a handful of steps. The demo therefore trains a SMALLER configuration (see
DEMO_MODEL) on smaller crops with a higher learning rate; the paper's settings are the CLI defaults.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import skimage

from optstereo.inference.engine import cpu_has_native_bf16
from pvm_labeler.common.datasets import discover, load_pair
from pvm_labeler.common.metrics import disparity_metrics
from pvm_labeler.shards import open_shard, read_index, read_sample

# One torch thread for training plus one loader worker fills the 2 cores; on a busy shared machine a second spinning
# OpenMP thread made small training steps 3-6x slower (measured at a load average of ~8).
# Smaller than the paper (feature_dim 256, hidden 128) so a CPU run learns something in minutes; say so in reports.
DEMO_MODEL = {"feature_dim": 64, "hidden_dim": 64, "head_dim": 64, "upsample_dim": 32}
BIN = Path(sys.executable).parent


def training_amp(choice: str) -> str:
    """The trainer's ``--amp`` for the demo: ``auto`` is bf16 where the CPU has bf16 in hardware
    (``cpu_has_native_bf16``: AVX512-BF16 or AMX; a demo step at 128x256 ran 2.0x faster than float32 on an AMX
    Xeon, so the 4 minutes buy twice the steps), float32 elsewhere (emulated bf16 is many times slower)."""
    if choice != "auto":
        return choice
    return "bf16" if cpu_has_native_bf16() else "none"


def _run(cmd: list[str], log: Path) -> None:
    """Echo and run a command; on failure show the tail of its output and stop."""
    print("$ " + " ".join(shlex.quote(c) for c in cmd), flush=True)
    t0 = time.perf_counter()
    with open(log, "a") as fh:
        proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=fh, text=True)
        fh.write(proc.stdout)
    for line in proc.stdout.strip().splitlines()[-4:]:
        print("  " + line, flush=True)
    if proc.returncode != 0:
        tail = log.read_text().splitlines()[-30:]
        sys.exit(f"command failed (exit {proc.returncode}); last log lines from {log}:\n" + "\n".join(tail))
    print(f"  ({time.perf_counter() - t0:.0f} s)", flush=True)


def _motorcycle_metrics(disp, gt) -> str:
    m = disparity_metrics(disp, gt)
    return f"EPE {m['epe']:.2f} px, bad-3 {m['bad3']:.1f} %, density {m['density']:.0f} %"


#: The shipped models the demo shows beside its own network (optstereo.pretrained.SHIPPED names).
SHOWN = ("pretrained", "pretrained-accurate")


def overview(out: Path, pred_npy: Path, shipped_npy: dict[str, Path], minutes: float = 4.0) -> Path:
    """left | PVM labels | GT / demo network (trained ``minutes``) | each shipped network for the motorcycle pair,
    metrics in the titles."""
    import matplotlib  # lazy: matplotlib.use("Agg") must run before pyplot loads

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: after matplotlib.use("Agg")

    sample = load_pair(next(r for r in discover("sample", None) if r.frame_id == "motorcycle"))
    label = None
    for path, ids in read_index(out / "labels").shards:
        if "motorcycle" in ids:
            with open_shard(path) as h5:
                label = read_sample(h5, "motorcycle").label
    pred = np.load(pred_npy)
    vmax = float(np.nanmax(sample.gt))
    fig, axes = plt.subplots(2, 3, figsize=(17, 8.5))
    panels = [("left image", sample.left), (f"PVM labels: {_motorcycle_metrics(label, sample.gt)}", label),
              ("ground truth", sample.gt),
              (f"demo OptStereo, {minutes:g} CPU min: {_motorcycle_metrics(pred, sample.gt)}", pred)]
    for name, path in shipped_npy.items():
        disp = np.load(path)
        panels.append((f"shipped {name}: {_motorcycle_metrics(disp, sample.gt)}", disp))
    panels += [(None, None)] * (6 - len(panels))
    cmap = plt.get_cmap("turbo").with_extremes(bad="black")  # "no value" black, as every picture of the toolkit
    shown = None
    for ax, (title, img) in zip(axes.ravel(), panels, strict=True):
        if title is None:
            ax.axis("off")
            continue
        if img is not None and img.ndim == 3:
            ax.imshow(img)
        elif img is not None:
            shown = ax.imshow(np.ma.masked_invalid(img), cmap=cmap, vmin=0, vmax=vmax)
        ax.set_title(title, fontsize=10)
        ax.axis("off")
    fig.tight_layout()
    if shown is not None:  # one scale for every disparity panel: the GT's range; beyond it, the top colour
        bar = fig.colorbar(shown, ax=axes.ravel().tolist(), fraction=0.015, pad=0.01, extend="max")
        bar.set_label("disparity (px); black: no value", fontsize=9)
    path = out / "overview.png"
    fig.savefig(path, dpi=80, bbox_inches="tight")  # the colour bar and its label inside the picture
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder")
    parser.add_argument("--minutes", type=float, default=4.0, help="training time budget (minutes)")
    parser.add_argument("--steps", type=int, default=2000, help="training steps (the time budget usually ends first)")
    parser.add_argument("--k", type=int, default=4, help="PVM pyramid scales for the sample")
    parser.add_argument("--amp", choices=("auto", "none", "bf16"), default="auto",
                        help="training precision; auto = bf16 autocast where the CPU has native bf16, else float32")
    args = parser.parse_args(argv)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    log = out / "demo.log"
    log.write_text("")
    t0 = time.perf_counter()
    os.environ.setdefault("PYTHONUNBUFFERED", "1")

    print("== 1/5 PVM pseudo-labels for the embedded sample dataset", flush=True)
    _run([str(BIN / "pvm-label"), "run", "--dataset", "sample", "--out", str(out / "labels"), "--k", str(args.k),
          "--max-disp", "64", "--jobs", "2", "--quiet", "--overwrite"], log)

    shutil.rmtree(out / "run", ignore_errors=True)  # a new run: the trainer refuses to mix two runs in one dir
    amp = training_amp(args.amp)
    print(f"== 2/5 self-supervised OptStereo training on CPU ({args.minutes:g} min budget, small demo model, "
          f"{'bf16 autocast' if amp == 'bf16' else 'float32'})", flush=True)
    model_opts = [x for k, v in DEMO_MODEL.items() for x in ("--set", f"model.{k}={v}")]
    _run([str(BIN / "optstereo-train"), "--labels", str(out / "labels"), "--out", str(out / "run"),
          "--steps", str(args.steps), "--max-minutes", str(args.minutes), "--crop", "128x256", "--batch-size", "2",
          "--iters", "4", "--lr", "4e-4", "--schedule", "constant", "--workers", "1", "--threads", "1",
          "--ckpt-every", "100", "--log-every", "10", "--device", "cpu", "--amp", amp, *model_opts], log)

    print("== 3/5 evaluation on the sample's ground truth (network, then the labels, one ruler)", flush=True)
    _run([str(BIN / "optstereo-eval"), "--checkpoint", str(out / "run"), "--dataset", "sample",
          "--out", str(out / "eval_network"), "--device", "cpu"], log)
    _run([str(BIN / "optstereo-eval"), "--labels", str(out / "labels"), "--out", str(out / "eval_labels")], log)

    print("== 4/5 prediction files for the motorcycle pair", flush=True)
    data = Path(skimage.__file__).parent / "data"
    _run([str(BIN / "optstereo-predict"), "--checkpoint", str(out / "run"), str(data / "motorcycle_left.png"),
          str(data / "motorcycle_right.png"), "--out", str(out / "predict"), "--format", "png", "--format", "pfm",
          "--format", "npy", "--format", "color", "--device", "cpu"], log)

    print(f"== 5/5 the shipped models ({', '.join(SHOWN)}; trained on unlabelled driving pairs only) on the same "
          "sample", flush=True)
    for name in SHOWN:
        _run([str(BIN / "optstereo-eval"), "--checkpoint", name, "--dataset", "sample",
              "--out", str(out / f"eval_{name}"), "--device", "cpu"], log)
        _run([str(BIN / "optstereo-predict"), "--checkpoint", name, str(data / "motorcycle_left.png"),
              str(data / "motorcycle_right.png"), "--out", str(out / f"predict_{name}"), "--format", "npy",
              "--format", "color", "--device", "cpu"], log)
    picture = overview(out, out / "predict" / "motorcycle_left.npy",
                       {name: out / f"predict_{name}" / "motorcycle_left.npy" for name in SHOWN}, args.minutes)

    net = json.loads((out / "eval_network" / "summary.json").read_text())
    lab = json.loads((out / "eval_labels" / "summary.json").read_text())
    shipped = {name: json.loads((out / f"eval_{name}" / "summary.json").read_text()) for name in SHOWN}
    steps = json.loads((out / "run" / "summary.json").read_text())["step"]
    print(f"\n== done in {time.perf_counter() - t0:.0f} s ({steps} training steps)")
    print(f"network on sample GT : EPE {net['epe']:.2f} px, bad3 {net['bad3']:.1f} %, D1 {net['d1_all']:.1f} % "
          f"(dense, {net['n_frames']} frames)")
    for name, pre in shipped.items():
        print(f"{name:<21}: EPE {pre['epe']:.2f} px, bad3 {pre['bad3']:.1f} %, D1 {pre['d1_all']:.1f} % "
              f"(dense, {pre['n_frames']} frames; trained on unlabelled driving pairs, never on this sample)")
    print(f"PVM labels           : EPE {lab['epe']:.2f} px, bad3 {lab['bad3']:.1f} %, density {lab['density']:.1f} %")
    print(f"pictures : {picture}, {out / 'eval_network' / 'maps'}, {out / 'eval_labels' / 'maps'}")
    print(f"reports  : {out / 'eval_network' / 'summary.md'}, {out / 'eval_labels' / 'summary.md'}")
    print(f"model    : {out / 'run' / 'last.pt'} (TensorBoard: {out / 'run' / 'tb'}); log: {log}")


if __name__ == "__main__":
    main()
