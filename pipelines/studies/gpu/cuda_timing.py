"""KITTI-size inference time on CUDA (issue 14: the paper reports 100 ms on an RTX 2080 Ti), for a lent GPU.

Times the network alone (inputs already on the GPU, padded 375x1242 -> 376x1248, test mode, 8 GRU iterations),
median of ``--repeats`` calls after ``--warmup``, each bracketed by ``torch.cuda.synchronize()``; and once
end to end through :func:`optstereo.inference.engine.infer` (uint8 numpy in, numpy out: host copies and padding
included). Rows: the shipped model (C = 128) and the paper-size network (C = 256, random weights: the time does
not depend on them), float32 / TF32 / bf16 / fp16 autocast; then the whole one-pass default at KITTI size as one
CUDA graph (:class:`optstereo.inference.graphed.GraphedPass`: uint8 numpy in, numpy out, replayed with no Python or
kernel-launch overhead) in bf16 / fp32 / TF32; and the shipped post-filter (wmedian) on the CPU and on the GPU. "fp32"
means TF32 off for convolutions too, which PyTorch leaves on by default.

    python -m pipelines.studies.gpu.cuda_timing --out $OUT/cuda_timing.json
    python -m pipelines.studies.gpu.cuda_timing --graphs-only --out $OUT/graphs.json   # GraphedPass beside infer()
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from optstereo.api import load_model
from optstereo.inference.engine import infer, inference_autocast
from optstereo.inference.graphed import GraphedPass
from optstereo.models import build_model
from pipelines.bench_models import cuda_seconds

KITTI_HW = (375, 1242)
PADDED_HW = (376, 1248)
ITERS = 8
PAPER_MS = 100.0  # the paper's OptStereo on an RTX 2080 Ti


def gpu_pair() -> tuple[torch.Tensor, torch.Tensor]:
    """A fixed random (1, 3, *PADDED_HW) pair in [0, 255], resident on the GPU (the time does not depend on it)."""
    gen = torch.Generator(device="cuda").manual_seed(0)
    return tuple(torch.rand(1, 3, *PADDED_HW, device="cuda", generator=gen) * 255 for _ in range(2))


def network_rows(model: torch.nn.Module, label: str, repeats: int, warmup: int) -> list[dict[str, Any]]:
    """One row per precision: the network's forward at PADDED_HW, inputs resident on the GPU."""
    dev = torch.device("cuda")
    left, right = gpu_pair()
    rows = []
    for precision in ("fp32", "tf32", "bf16", "fp16"):
        set_tf32(precision == "tf32")
        amp = precision if precision in ("bf16", "fp16") else "none"

        @torch.inference_mode()
        def forward(amp: str = amp) -> None:
            with inference_autocast(amp, dev):
                model(left, right, iters=ITERS, test_mode=True)

        torch.cuda.reset_peak_memory_stats()
        seconds = cuda_seconds(forward, repeats, warmup)
        rows.append({"model": label, "precision": precision, "ms": round(seconds * 1e3, 2),
                     "vs_paper_100ms": round(seconds * 1e3 / PAPER_MS, 3),
                     "peak_gpu_mib": round(torch.cuda.max_memory_allocated() / 2**20, 1)})
        print(rows[-1], flush=True)
    set_tf32(False)
    return rows


def set_tf32(on: bool) -> None:
    """TF32 for cuDNN convolutions and matmuls together (PyTorch's defaults differ: convolutions on, matmuls off)."""
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = on


def graphed_rows(model: torch.nn.Module, label: str, repeats: int, warmup: int,
                 eager: bool = False) -> list[dict[str, Any]]:
    """``optstereo.inference.graphed.GraphedPass`` end to end at KITTI size (uint8 numpy in, numpy out: the host
    copies, padding and the network captured as one CUDA graph and replayed), bf16 / fp32 (TF32 off) / TF32; with
    ``eager`` each beside ``infer`` at the same precision. A failed capture is a row with its error, not a crash."""
    left, right = kitti_pair()
    rows = []
    for precision in ("bf16", "fp32", "tf32"):
        set_tf32(precision == "tf32")  # read when the graph is captured: the kernels are fixed in it
        amp = "bf16" if precision == "bf16" else "none"
        row: dict[str, Any] = {"model": label, "precision": precision, "what": "GraphedPass end to end (CUDA graph)"}
        try:
            graphed = GraphedPass(model, KITTI_HW, device="cuda", iters=ITERS, amp=amp, scale=1.0)
            row["ms"] = round(cuda_seconds(lambda graphed=graphed: graphed(left, right), repeats, warmup) * 1e3, 2)
            row["vs_paper_100ms"] = round(row["ms"] / PAPER_MS, 3)
            del graphed  # its graph's memory pool goes with it
        except (RuntimeError, ValueError) as exc:  # a capture can fail (a host sync inside forward): record why
            row["error"] = f"{type(exc).__name__}: {str(exc)[:300]}"
        rows.append(row)
        print(row, flush=True)
        if eager:
            rows.append(end_to_end_row(model, repeats, warmup, label, amp, ITERS) | {"precision": precision})
    set_tf32(False)
    return rows


def kitti_pair() -> tuple[np.ndarray, np.ndarray]:
    """A fixed random KITTI-size uint8 pair (the time does not depend on it), the right view shifted by 8 px."""
    left = np.random.default_rng(0).integers(0, 256, (*KITTI_HW, 3), dtype=np.uint8)
    return left, np.ascontiguousarray(np.roll(left, -8, axis=1))


def end_to_end_row(model: torch.nn.Module, repeats: int, warmup: int, label: str = "shipped", amp: str = "bf16",
                   iters: int | None = ITERS) -> dict[str, Any]:
    """``infer`` on uint8 numpy arrays of KITTI size (host-to-device, the model's resizing and passes, padding,
    unpadding, its post-filter and the copy back)."""
    left, right = kitti_pair()
    seconds = cuda_seconds(lambda: infer(model, left, right, iters=iters, device="cuda", amp=amp),
                            repeats, warmup)
    row = {"model": label, "precision": amp, "what": "infer() end to end", "ms": round(seconds * 1e3, 2)}
    print(row, flush=True)
    return row


def wmedian_rows(repeats: int, warmup: int) -> list[dict[str, Any]]:
    """The shipped post-filter (``refine: wmedian``) on a KITTI-size disparity: the CPU's numba kernel (what infer
    ran on every device before) against the torch one on the GPU (what infer runs on CUDA)."""
    from optstereo.inference.refine_torch import weighted_median_torch
    from pvm_labeler.refine import weighted_median

    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (*KITTI_HW, 3), dtype=np.uint8)
    coarse = rng.uniform(0, 100, (KITTI_HW[0] // 8 + 1, KITTI_HW[1] // 8 + 1)).astype(np.float32)
    disp = np.kron(coarse, np.ones((8, 8), np.float32))[:KITTI_HW[0], :KITTI_HW[1]].copy()  # 8-px blocks: edges
    rows = []
    for what, fn in (("wmedian, numba on the CPU", lambda: weighted_median(disp, image)),
                     ("wmedian, torch on CUDA", lambda: weighted_median_torch(disp, image, device="cuda"))):
        seconds = cuda_seconds(fn, max(3, repeats // 4), min(warmup, 2))
        rows.append({"what": what, "input": f"{KITTI_HW[0]}x{KITTI_HW[1]}", "ms": round(seconds * 1e3, 2)})
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--graphs-only", action="store_true",
                        help="only the CUDA-graph rows (GraphedPass) and the shipped model's infer() beside them")
    parser.add_argument("--end-to-end", nargs="+", metavar="NAME=CHECKPOINT",
                        help="only infer() end to end (bf16 and none) of these checkpoints, with their own settings")
    args = parser.parse_args()
    if not torch.cuda.is_available():
        raise SystemExit("cuda_timing: no CUDA device")
    if args.end_to_end:
        rows = []
        for spec in args.end_to_end:
            name, _, path = spec.partition("=")
            model = load_model(path, device="cuda")
            rows += [end_to_end_row(model, args.repeats, args.warmup, name, amp, None) for amp in ("bf16", "none")]
        report = {"device": torch.cuda.get_device_name(), "torch": torch.__version__,
                  "input": "x".join(map(str, KITTI_HW)), "synchronised": True, "rows": rows}
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(report, indent=2) + "\n")
        return
    shipped = load_model("pretrained", device="cuda")
    torch.manual_seed(0)
    paper = build_model("optstereo", iters=ITERS).cuda().eval()  # the defaults are the paper's sizes
    rows = []
    if not args.graphs_only:
        rows += network_rows(shipped, "shipped (C=128)", args.repeats, args.warmup)
        rows += network_rows(paper, "paper size (C=256)", args.repeats, args.warmup)
        rows.append(end_to_end_row(shipped, args.repeats, args.warmup))
        rows += wmedian_rows(args.repeats, args.warmup)
    rows += graphed_rows(shipped, "shipped (C=128)", args.repeats, args.warmup, eager=args.graphs_only)
    rows += graphed_rows(paper, "paper size (C=256)", args.repeats, args.warmup)
    report = {"device": torch.cuda.get_device_name(), "torch": torch.__version__, "cuda": torch.version.cuda,
              "input": f"{KITTI_HW[0]}x{KITTI_HW[1]} padded to {PADDED_HW[0]}x{PADDED_HW[1]}", "iters": ITERS,
              "repeats": args.repeats, "warmup": args.warmup, "rows": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
