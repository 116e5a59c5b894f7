"""`make bench` section "export": the shipped model on a real KITTI frame, eager torch vs onnxruntime (same run).

Both run the same weights (``--checkpoint pretrained``) on KITTI 2015 frame 000000 (375x1242, padded to a multiple of
8), at the model's own input scale and at scale 1, with 2 threads each, in alternation (so both see the same load),
median of ``REPEATS`` after a warm-up: torch ``inference_mode`` (the ``optstereo-predict`` path) and an onnxruntime
CPU session of ``optstereo-export --format onnx`` (the default batch-1 graph). The ratio onnxruntime / torch at the
model's own scale is the figure to compare (target <= 0.8 on this CPU); the outputs' difference too. Each repeat
also gives a paired ratio (that repeat's two times, run back to back): their spread shows how much of the ratio is
the VM's noise.
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from optstereo.api import load_model
from optstereo.export import export, infer_onnx, onnx_session
from optstereo.inference.engine import infer, model_inference_config
from pvm_labeler.common.io import read_image

THREADS = 2
REPEATS = int(os.environ.get("PVS_BENCH_REPEATS", "5"))
TARGET = 0.8


def _medians(fns: dict[str, Callable[[], Any]], repeats: int = REPEATS) -> dict[str, float]:
    """Median seconds of each function, run in alternation (one warm-up each) so both see the same machine load."""
    return {name: statistics.median(values) for name, values in _timings(fns, repeats).items()}


def paired_ratios(num: list[float], den: list[float]) -> dict[str, float]:
    """Min, median and max of the per-repeat ratios num[i] / den[i] (two timings taken back to back)."""
    if len(num) != len(den) or not num:
        raise ValueError(f"need two equally long, non-empty timing lists, got {len(num)} and {len(den)}")
    ratios = sorted(a / b for a, b in zip(num, den, strict=True))
    return {"min": ratios[0], "median": statistics.median(ratios), "max": ratios[-1]}


def _timings(fns: dict[str, Callable[[], Any]], repeats: int, warmup: bool = True) -> dict[str, list[float]]:
    """Seconds of each call of each function, run in alternation after one warm-up each (unless the caller has
    already run them)."""
    times: dict[str, list[float]] = {name: [] for name in fns}
    for fn in fns.values() if warmup else ():
        fn()
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    return times


def _compare(model: Any, session: Any, left: np.ndarray, right: np.ndarray, scale: float) -> dict[str, Any]:
    """torch vs onnxruntime on one pair at one input scale: medians, ratio, paired spread, output difference."""
    fns = {"torch": lambda: infer(model, left, right, scale=scale),
           "onnxruntime": lambda: infer_onnx(session, left, right, scale=scale)}
    diff = np.abs(fns["onnxruntime"]() - fns["torch"]())  # these first calls are the warm-up, too
    times = _timings(fns, REPEATS, warmup=False)
    torch_s, ort_s = statistics.median(times["torch"]), statistics.median(times["onnxruntime"])
    return {"input_scale": scale, "torch_s": torch_s, "onnxruntime_s": ort_s, "ratio": ort_s / torch_s,
            "paired_ratio": paired_ratios(times["onnxruntime"], times["torch"]),
            "mean_abs_diff_px": float(diff.mean()), "max_abs_diff_px": float(diff.max())}


def run(shared: Path) -> dict[str, Any]:
    torch.set_num_threads(THREADS)
    base = Path(shared) / "kitti15/training"
    left, right = read_image(base / "image_2/000000_10.png"), read_image(base / "image_3/000000_10.png")
    model = load_model("pretrained")
    # The shipped model's own input scale is the predict path (the headline); scale 1 is the frame as it is, a
    # workload that stays put when a version with another input scale ships (the ratio depends on the frame size).
    scales = dict.fromkeys((model_inference_config(model).scale, 1.0))
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        onnx_file = export(model, Path(tmp) / "pretrained.onnx")
        export_s = time.perf_counter() - t0
        session = onnx_session(onnx_file, threads=THREADS)
        rows = [_compare(model, session, left, right, scale) for scale in scales]
    results = {"threads": THREADS, "repeats": REPEATS, "frame": "kitti15 000000_10 (375x1242)",
               "iters": model.iters, **rows[0], "by_scale": rows, "export_s": export_s,
               "load_avg": os.getloadavg()[0]}
    verdict = "met" if results["ratio"] <= TARGET else "not met"
    lines = [
        f"Shipped model, {results['frame']}, {model.iters} GRU iterations, {THREADS} threads, median of {REPEATS} "
        "runs of each, alternating; first at the model's own input scale (the `optstereo-predict` path), then at "
        "scale 1 (the frame as it is).",
        "",
        "| input scale | torch eager (inference_mode) s | onnxruntime CPU (opset 18) s | ratio | paired ratios | "
        "mean / max diff px |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for i, row in enumerate(rows):
        ratio = f"**{row['ratio']:.2f}** (target <= {TARGET}: {verdict})" if i == 0 else f"{row['ratio']:.2f}"
        spread = row["paired_ratio"]
        lines.append(f"| {row['input_scale']:g} | {row['torch_s']:.3f} | {row['onnxruntime_s']:.3f} | {ratio} | "
                     f"{spread['min']:.2f}-{spread['max']:.2f} (median {spread['median']:.2f}) | "
                     f"{row['mean_abs_diff_px']:.4f} / {row['max_abs_diff_px']:.4f} |")
    lines += ["", f"The export took {export_s:.0f} s; load average {results['load_avg']:.1f}. Paired ratios: each "
              "repeat's two times, run back to back."]
    return {"title": "Export (torch vs onnxruntime)", "results": results, "markdown": "\n".join(lines)}
