"""`make bench` section "network": OptStereo size, FLOPs and CPU speed (training step and inference).

Measured in this process with ``torch.set_num_threads(2)``:
- parameter count (total and per part) of the paper-size network (C = 256, hidden 128, 4 levels, d = 4);
- GFLOP of one training forward+backward (320x736, batch 2, N_s = 8) and of one inference (384x1248, 8 iters),
  counted by ``torch.utils.flop_counter`` (convs/matmuls only): load-independent, unlike the timings;
- training step seconds (forward + backward + Adam, PVStereoLoss with lambda_r = lambda_s = 0.1) at 320x736,
  batch 2, 8 iterations: default (on CPU the encoder and upsampler run one image per call), both on the whole
  batch per call, channels_last, the convex upsampler and bf16 autocast;
- inference seconds at 384x1248 (1 pair), 8 iterations, test_mode: no_grad, inference_mode, inference_mode with
  batched encoder and upsampler calls, inference_mode + channels_last, inference_mode + bf16 autocast,
  torch.compile (compile time reported separately; skipped if it fails). bf16 pays off on CPUs with native
  bf16 (AVX512-BF16 or AMX);
- an sgemm throughput probe (GFLOP/s of a 1024^3 float32 matmul) before and after, and the load average,
  so a reader can tell how busy the shared machine was.

There is no RAFT-Stereo in this environment, so no same-run baseline exists. The ratios are against the
issue's quoted figures for RAFT-Stereo configured closest to OptStereo on this machine (train step 9.5 s,
inference 3.1 s); they are only indicative when other jobs share the CPU.
"""

from __future__ import annotations

import contextlib
import logging
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch.utils.flop_counter import FlopCounterMode

from optstereo.inference.engine import cpu_has_native_bf16
from optstereo.models import build_model
from optstereo.training.losses import PVStereoLoss

log = logging.getLogger(__name__)

THREADS = 2
TRAIN_SHAPE = (2, 3, 320, 736)
INFER_SHAPE = (1, 3, 384, 1248)
ITERS = 8
RAFT_STEREO_QUOTED = {"train_step_s": 9.5, "infer_s": 3.1}  # issue 4, measured on this machine, not here
TARGET_RATIO = 0.5
REPEATS = int(os.environ.get("PVS_BENCH_REPEATS", "3"))


def _median_time(fn: Callable[[], Any], repeats: int, warmup: int = 1) -> dict[str, Any]:
    """Median wall seconds and median process CPU seconds (all threads) of ``fn``.

    On a shared machine the wall time grows with the other jobs' load, while the CPU time this process
    spends is nearly load-independent; cpu_s / THREADS estimates the wall time on an idle machine (an upper
    bound: OpenMP threads spin while waiting, and that counts as CPU time).
    """
    for _ in range(warmup):  # oneDNN primitive caches, allocator
        fn()
    walls, cpus = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
    return {
        "median_s": statistics.median(walls),
        "times_s": walls,
        "cpu_s": statistics.median(cpus),
        "idle_estimate_s": statistics.median(cpus) / THREADS,
    }


def _gemm_gflops() -> float:
    a = torch.randn(1024, 1024)
    b = torch.randn(1024, 1024)
    sec = _median_time(lambda: a @ b, repeats=5)["median_s"]
    return 2 * 1024**3 / sec / 1e9


def _inputs(shape: tuple[int, ...], channels_last: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    left = torch.rand(shape, generator=g) * 255
    right = torch.roll(left, shifts=-8, dims=-1)  # a plausible pair: constant 8 px disparity
    if channels_last:
        left = left.contiguous(memory_format=torch.channels_last)
        right = right.contiguous(memory_format=torch.channels_last)
    return left, right


def _param_counts(model: torch.nn.Module) -> dict[str, int]:
    counts = {name: sum(p.numel() for p in child.parameters()) for name, child in model.named_children()}
    counts["total"] = sum(p.numel() for p in model.parameters())
    return counts


def _autocast(bf16: bool) -> contextlib.AbstractContextManager:
    """bf16 autocast on CPU (pays off with AVX512-BF16/AMX; the trainer's --amp bf16), else a null context."""
    return torch.autocast("cpu", dtype=torch.bfloat16) if bf16 else contextlib.nullcontext()


def _train_step_fn(upsampler: str = "conv", channels_last: bool = False, bf16: bool = False,
                   image_chunk: int | None = None) -> Callable[[], None]:
    torch.manual_seed(0)
    model = build_model("optstereo", iters=ITERS, upsampler=upsampler).train()
    model.image_chunk = image_chunk
    if channels_last:
        model = model.to(memory_format=torch.channels_last)
    loss_fn = PVStereoLoss(gamma=0.8, lambda_r=0.1, lambda_s=0.1)
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)
    left, right = _inputs(TRAIN_SHAPE, channels_last)
    b, _, h, w = TRAIN_SHAPE
    label = torch.full((b, 1, h, w), 8.0)
    valid = torch.rand(b, 1, h, w, generator=torch.Generator().manual_seed(1)) < 0.4  # semi-dense, like PVM

    def step() -> None:
        with _autocast(bf16):
            preds = model(left, right)
        total, _ = loss_fn([p.float() for p in preds], left, right, label, valid)
        opt.zero_grad(set_to_none=True)
        total.backward()
        opt.step()

    return step


def _infer_fn(mode: str) -> tuple[Callable[[], None], float]:
    """mode: no_grad | inference_mode | inference_mode+batched_calls | inference_mode+channels_last |
    inference_mode+bf16 | compile.

    Returns (fn, setup seconds)."""
    torch.manual_seed(0)
    model = build_model("optstereo", iters=ITERS).eval()
    if mode.endswith("batched_calls"):
        model.image_chunk = 0  # whole batch per encoder and upsampler call (the CPU default is one image per call)
    channels_last = mode.endswith("channels_last")
    if channels_last:
        model = model.to(memory_format=torch.channels_last)
    left, right = _inputs(INFER_SHAPE, channels_last)
    setup = 0.0
    net: Callable[..., Any] = model
    if mode == "compile":
        net = torch.compile(model)
        t0 = time.perf_counter()
        with torch.no_grad():
            net(left, right, iters=ITERS, test_mode=True)  # first call compiles
        setup = time.perf_counter() - t0

    def run() -> None:
        ctx = torch.no_grad() if mode in ("no_grad", "compile") else torch.inference_mode()
        with ctx, _autocast(mode.endswith("bf16")):
            net(left, right, iters=ITERS, test_mode=True)

    return run, setup


def _count_gflops(fn: Callable[[], None]) -> float:
    counter = FlopCounterMode(display=False)
    with counter:
        fn()
    return counter.get_total_flops() / 1e9


def _measure_flops() -> dict[str, float]:
    torch.manual_seed(0)
    model = build_model("optstereo", iters=ITERS).train()
    left, right = _inputs(TRAIN_SHAPE)

    def train_fwd_bwd() -> None:
        sum(p.mean() for p in model(left, right)).backward()

    il, ir = _inputs(INFER_SHAPE)

    def infer() -> None:
        with torch.no_grad():
            model.eval()(il, ir, iters=ITERS, test_mode=True)

    return {"train_fwd_bwd_gflop": _count_gflops(train_fwd_bwd), "infer_gflop": _count_gflops(infer)}


def run(shared: Path) -> dict[str, Any]:
    """Bench entry point (``shared`` is unused: the inputs are synthetic tensors of the stated sizes)."""
    torch.set_num_threads(THREADS)
    results: dict[str, Any] = {
        "threads": THREADS,
        "torch": torch.__version__,
        "repeats": REPEATS,
        "load_avg_start": os.getloadavg()[0],
        "gemm_gflops_start": _gemm_gflops(),
        "params": _param_counts(build_model("optstereo")),
        "flops": _measure_flops(),
        "train": {},
        "infer": {},
        "quoted_raft_stereo": RAFT_STEREO_QUOTED,
        "native_bf16": cpu_has_native_bf16(),
    }
    for label, kwargs in (
        ("default", {}),
        ("batched_calls", {"image_chunk": 0}),
        ("channels_last", {"channels_last": True}),
        ("convex_upsampler", {"upsampler": "convex"}),
        ("bf16_autocast", {"bf16": True}),
    ):
        if kwargs.get("bf16") and not results["native_bf16"]:
            results["train"][label] = {"skipped": "no native bf16 on this CPU (bf16 would be emulated)"}
            continue
        log.info("network bench: train step %s", label)
        results["train"][label] = _median_time(_train_step_fn(**kwargs), REPEATS)
    for mode in ("no_grad", "inference_mode", "inference_mode+batched_calls", "inference_mode+channels_last",
                 "inference_mode+bf16", "compile"):
        if mode.endswith("bf16") and not results["native_bf16"]:
            results["infer"][mode] = {"skipped": "no native bf16 on this CPU (bf16 would be emulated)"}
            continue
        log.info("network bench: inference %s", mode)
        try:
            fn, setup = _infer_fn(mode)
            timing = _median_time(fn, REPEATS)
        except Exception as exc:  # noqa: BLE001 -- torch.compile can fail in many ways on CPU; report, don't abort
            log.warning("inference mode %s failed: %s", mode, exc)
            results["infer"][mode] = {"error": f"{type(exc).__name__}: {exc}"[:300]}
            continue
        results["infer"][mode] = {**timing, "setup_s": setup}
    results["gemm_gflops_end"] = _gemm_gflops()
    results["load_avg_end"] = os.getloadavg()[0]
    return {"title": "Network (OptStereo on CPU)", "results": results, "markdown": _markdown(results)}


def _markdown(r: dict[str, Any]) -> str:
    p = r["params"]
    f = r["flops"]
    q = r["quoted_raft_stereo"]
    lines = [
        f"Paper-size OptStereo (C = 256, hidden 128, 4 levels, d = 4, conv upsampler), {r['threads']} threads, "
        f"torch {r['torch']}, median of {r['repeats']} after one warm-up.",
        "",
        f"- Parameters: **{p['total']:,}** (" + ", ".join(f"{k} {v:,}" for k, v in p.items() if k != "total") + ")",
        f"- GFLOP (convs + matmuls): training fwd+bwd 320x736 batch 2, 8 iters: {f['train_fwd_bwd_gflop']:.0f}; "
        f"inference 384x1248, 8 iters: {f['infer_gflop']:.0f}",
        f"- Machine state: load average {r['load_avg_start']:.1f} -> {r['load_avg_end']:.1f} on 2 cores; sgemm "
        f"probe {r['gemm_gflops_start']:.0f} -> {r['gemm_gflops_end']:.0f} GFLOP/s (other jobs share the CPU).",
        "",
        "Wall = median wall seconds in this (shared) run; idle est. = median process CPU seconds / 2 threads, "
        "an estimate of the wall time on an idle machine. Ratios are against the issue's RAFT-Stereo figures.",
        "",
        f"| measurement | wall s | idle est. s | wall / quoted | idle est. / quoted | target <= {TARGET_RATIO} |",
        "| --- | --- | --- | --- | --- | --- |",
    ]

    def row(name: str, m: dict[str, Any], quoted: float) -> str:
        wall, idle = m["median_s"] / quoted, m["idle_estimate_s"] / quoted
        ok = "yes" if min(wall, idle) <= TARGET_RATIO else "no"
        return f"| {name} | {m['median_s']:.2f} | {m['idle_estimate_s']:.2f} | {wall:.2f} | {idle:.2f} | {ok} |"

    for label, m in r["train"].items():
        if "skipped" in m:
            lines.append(f"| train step 320x736 b2, {label} | skipped: {m['skipped']} | | | | |")
            continue
        lines.append(row(f"train step 320x736 b2, {label}", m, q["train_step_s"]))
    for mode, m in r["infer"].items():
        if "skipped" in m:
            lines.append(f"| inference 384x1248, {mode} | skipped: {m['skipped']} | | | | |")
            continue
        if "error" in m:
            lines.append(f"| inference 384x1248, {mode} | failed: {m['error'][:80]} | | | | |")
            continue
        extra = f" (compile {m['setup_s']:.0f} s)" if m.get("setup_s") else ""
        lines.append(row(f"inference 384x1248 8 it, {mode}{extra}", m, q["infer_s"]))
    lines += [
        "",
        "RAFT-Stereo is not installed here, so its figures are the issue's quoted ones (train step 9.5 s, "
        "inference 3.1 s, measured on this machine when it was not shared), not a same-run baseline.",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    import json

    logging.basicConfig(level=logging.INFO)
    out = run(Path("../shared/data"))
    print(out["markdown"])
    print(json.dumps(out["results"], indent=2, default=float))
