"""`make bench` section "models": each shipped model's seconds per KITTI frame against OpenCV's SGBM, same run.

For every shipped name (``optstereo.pretrained.SHIPPED``) the end-to-end ``optstereo.inference.engine.infer`` of the
model as ``optstereo.api.load_model`` gives it (the engineered CPU pass of ``optstereo.inference.fastpath``, its GRU
convolutions Winograd or direct, whichever the machine runs faster) with its own settings (resize, passes,
post-filter; float32, 2 threads, model loaded once), the same with Winograd forced
(``fastpath.engineering(True, winograd=True)``), with direct GRU convolutions forced (``winograd=False``: issue
52's first step alone) and with the plain
``OptStereo.forward`` (``fastpath.engineering(False)``: the time before issue 52), timed on the same KITTI 2015 frames
as OpenCV StereoSGBM (MODE_HH, 192 disparities, blockSize 5: the labeler bench's baseline; single-threaded in
OpenCV), all alternating frame by frame so that load on a shared machine hits them alike. The ratio is the
median over frames of (model seconds / SGBM seconds on that frame); the default model's target is <= 2.0 (issue 52;
issue 42's was 3.0), the fast model's <= 0.5. With CUDA present, GPU rows per model: ``infer`` and
``optstereo.inference.graphed.GraphedPass`` (the one-pass default as one CUDA graph) in bf16 and float32, end to end,
synchronised, median of 10 after 3 warm-up calls (issue 42's target for the default: <= 15 ms in bf16; issue 52's,
graphed: <= 10 ms on an H100).

Beside them, in the same run, `pvm-label match` (issue 52): ``pvm_labeler.match.match_arrays`` (grey, census SGM of
the left view over 192 disparities, row fill: what the command does between reading and writing) with numba on the
same 2 threads, alternating with SGBM-HH frame by frame; its target is <= 0.5x SGBM's time. Its row also gives both
maps' bad-3 on all 15 KITTI 2015 GT frames (occ GT, else noc; fast enough to score them all), SGBM's holes filled by
the same row fill so that the two matchers, not their fills, are compared.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from optstereo.api import load_model
from optstereo.inference import fastpath
from optstereo.inference.engine import infer
from optstereo.inference.fastpath import engineering
from optstereo.inference.graphed import GraphedPass
from optstereo.pretrained import SHIPPED
from pipelines.bench_labeler import _opencv
from pvm_labeler.common.datasets import discover, load_pair
from pvm_labeler.common.io import read_image
from pvm_labeler.common.metrics import MetricAccumulator
from pvm_labeler.common.version import cpuinfo_flags
from pvm_labeler.dense import fill_rows_nearest
from pvm_labeler.match import match_arrays
from pvm_labeler.parallel import thread_budget

THREADS = 2
FRAMES = ("000000", "000005", "000010", "000015")
REPEATS = int(os.environ.get("PVS_BENCH_REPEATS", "3"))
TARGETS = {"pretrained": 2.0, "pretrained-fast": 0.5}
MATCH_TARGET = 0.5
#: Environment capping a process's math libraries at AVX2: on an AVX-512 CPU a child run with it stands in for an
#: AVX2-only one (on a Zen 5 EPYC it put version 15 at 2.8-2.9x SGBM-HH against 2.66x measured on an AVX2 EPYC).
AVX2_PROXY = {"ONEDNN_MAX_CPU_ISA": "AVX2", "ATEN_CPU_CAPABILITY": "avx2", "MKL_ENABLE_INSTRUCTIONS": "AVX2"}


def _seconds(fn: Callable[[], Any], repeats: int) -> float:
    """Median wall seconds of ``fn`` over ``repeats`` calls after one warm-up call."""
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def beside_sgbm(model: torch.nn.Module, frames: list[tuple[np.ndarray, np.ndarray]], repeats: int,
                sgbm: Any, run: Callable[..., Any] = infer) -> dict[str, float]:
    """``run(model, left, right)`` (``infer``) timed on each frame right after OpenCV's ``sgbm`` on it: median
    seconds per frame of each and the median of the per-frame ratios (the machine's drift cancels frame by frame)."""
    model_s, sgbm_s = [], []
    for left, right in frames:
        sgbm_s.append(_seconds(functools.partial(sgbm.compute, left, right), repeats))
        model_s.append(_seconds(functools.partial(run, model, left, right), repeats))
    return {"s_per_frame": statistics.median(model_s), "sgbm_s": statistics.median(sgbm_s),
            "ratio": statistics.median(m / s for m, s in zip(model_s, sgbm_s, strict=True))}


def _frames(shared: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    base = Path(shared) / "kitti15/training"
    return [(read_image(base / f"image_2/{f}_10.png"), read_image(base / f"image_3/{f}_10.png")) for f in FRAMES]


def _scored(shared: Path) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(left, right, GT) of every KITTI 2015 GT frame through the project's reader (GT: occ if present, else noc)."""
    samples = [load_pair(ref) for ref in discover("kitti15", Path(shared) / "kitti15")]
    return [(s.left, s.right, s.gt) for s in samples if s.gt is not None]


def plain_infer(model: torch.nn.Module, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """``infer`` through the plain ``OptStereo.forward`` (no engineered CPU pass): the time before issue 52."""
    with engineering(False):
        return infer(model, left, right)


def float32_infer(model: torch.nn.Module, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """``infer`` through the engineered pass with its encoder in float32 (no int8, ``optstereo.inference.int8``)."""
    with engineering(True, int8=False):
        return infer(model, left, right)


def winograd_infer(model: torch.nn.Module, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """``infer`` through the engineered pass with Winograd GRU convolutions forced (no per-machine choice)."""
    with engineering(True, winograd=True):
        return infer(model, left, right)


def direct_infer(model: torch.nn.Module, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """``infer`` through the engineered pass with direct GRU convolutions (no Winograd): issue 52's first step."""
    with engineering(True, winograd=False):
        return infer(model, left, right)


def cpu_rows(models: dict[str, torch.nn.Module], frames: list[tuple[np.ndarray, np.ndarray]],
             repeats: int = REPEATS) -> list[dict[str, Any]]:
    """Per model: median seconds per frame (the path users get, the same with Winograd forced, without it, the plain
    one), SGBM's on the same frames, and the median per-frame ratios."""
    sgbm = _opencv(cv2.STEREO_SGBM_MODE_HH)
    rows = []
    for name, model in models.items():
        model_s, float_s, winograd_s, direct_s, plain_s, sgbm_s = [], [], [], [], [], []
        config = getattr(model, "inference_config", None)
        # a multi-pass model: one timed run each (KITTI frames are not small pairs: no adaptive pass)
        runs = 1 if config is not None and config.passes_for(enlarged=False) > 1 else repeats
        for left, right in frames:
            sgbm_s.append(_seconds(functools.partial(sgbm.compute, left, right), runs))
            model_s.append(_seconds(functools.partial(infer, model, left, right), runs))
            float_s.append(_seconds(functools.partial(float32_infer, model, left, right), runs))
            winograd_s.append(_seconds(functools.partial(winograd_infer, model, left, right), runs))
            direct_s.append(_seconds(functools.partial(direct_infer, model, left, right), runs))
            plain_s.append(_seconds(functools.partial(plain_infer, model, left, right), runs))
        ratio = statistics.median(m / s for m, s in zip(model_s, sgbm_s, strict=True))
        target = TARGETS.get(name)
        rows.append({"model": name, "s_per_frame": statistics.median(model_s), "sgbm_s": statistics.median(sgbm_s),
                     "ratio": ratio, "int8": fastpath.int8_encoder(model) is not None,
                     "float32_s_per_frame": statistics.median(float_s),
                     "float32_ratio": statistics.median(f / s for f, s in zip(float_s, sgbm_s, strict=True)),
                     "winograd_s_per_frame": statistics.median(winograd_s),
                     "winograd_ratio": statistics.median(w / s for w, s in zip(winograd_s, sgbm_s, strict=True)),
                     "direct_s_per_frame": statistics.median(direct_s),
                     "direct_ratio": statistics.median(d / s for d, s in zip(direct_s, sgbm_s, strict=True)),
                     "plain_s_per_frame": statistics.median(plain_s),
                     "plain_ratio": statistics.median(p / s for p, s in zip(plain_s, sgbm_s, strict=True)),
                     "target": target,
                     "verdict": None if target is None else ("met" if ratio <= target else "not met")})
    return rows


def _match(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    with thread_budget(THREADS):
        return match_arrays(left, right)


def _sgbm_filled(sgbm: Any, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """SGBM's disparity in px (fixed point / 16) with its invalid pixels (< 0) filled along the row like match's."""
    disp = sgbm.compute(left, right).astype(np.float32) / 16
    return fill_rows_nearest(np.where(disp >= 0, disp, np.nan).astype(np.float32))


def match_row(frames: list[tuple[np.ndarray, np.ndarray]], scored: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
              repeats: int = REPEATS) -> dict[str, Any]:
    """`pvm-label match`'s seconds per frame, SGBM-HH's on the same ``frames``, the median per-frame ratio, and both
    maps' pooled bad-3 (%) on the ``scored`` (left, right, GT) triples."""
    sgbm = _opencv(cv2.STEREO_SGBM_MODE_HH)
    ratios, match_s, sgbm_s = [], [], []
    for left, right in frames:
        t_sgbm = _seconds(functools.partial(sgbm.compute, left, right), repeats)
        t_match = _seconds(functools.partial(_match, left, right), repeats)
        match_s.append(t_match)
        sgbm_s.append(t_sgbm)
        ratios.append(t_match / t_sgbm)
    acc = {"match": MetricAccumulator(), "sgbm": MetricAccumulator()}
    for left, right, gt in scored:
        acc["match"].update(_match(left, right), gt)
        acc["sgbm"].update(_sgbm_filled(sgbm, left, right), gt)
    ratio = statistics.median(ratios)
    bad3 = {name: a.compute()["bad3"] for name, a in acc.items()}
    return {"model": "pvm-label match", "s_per_frame": statistics.median(match_s), "sgbm_s": statistics.median(sgbm_s),
            "ratio": ratio, "target": MATCH_TARGET, "verdict": "met" if ratio <= MATCH_TARGET else "not met",
            "bad3": bad3["match"], "sgbm_bad3": bad3["sgbm"], "bad3_ratio": bad3["match"] / bad3["sgbm"]}


def gpu_rows(models: dict[str, torch.nn.Module], left: np.ndarray, right: np.ndarray) -> list[dict[str, Any]]:
    """Per model and precision: synchronised milliseconds on CUDA of ``infer`` (eager) and of
    ``optstereo.inference.graphed.GraphedPass`` (the one-pass default as one CUDA graph; a model whose settings it
    cannot capture, or a failed capture, gives a row with the error instead), both uint8 numpy in, numpy out; empty
    without CUDA."""
    if not torch.cuda.is_available():
        return []
    rows = []
    for name, model in models.items():
        model = model.cuda()
        for amp, precision in (("bf16", "bf16"), ("none", "fp32")):
            row = {"model": name, "path": "eager", "precision": precision, "device": torch.cuda.get_device_name()}
            # scale 1 on both paths: a graph captures no resize (the CPU default runs KITTI frames at 1.125, T8)
            rows.append(row | {"ms": 1e3 * cuda_seconds(functools.partial(infer, model, left, right, device="cuda",
                                                                            amp=amp, scale=1.0))})
            try:
                graphed = GraphedPass(model, left.shape[:2], device="cuda", amp=amp, scale=1.0)
                ms = 1e3 * cuda_seconds(functools.partial(graphed, left, right))
                rows.append(row | {"path": "graphed", "ms": ms})
                del graphed  # frees its graph's memory pool before the next capture
            except (RuntimeError, ValueError) as exc:  # settings it cannot capture, or a failed capture: say why
                rows.append(row | {"path": "graphed", "ms": None, "error": f"{type(exc).__name__}: {exc}"[:200]})
        model.cpu()
    return rows


def cuda_seconds(fn: Callable[[], Any], repeats: int = 10, warmup: int = 3) -> float:
    """Median wall seconds of ``fn`` with the GPU drained before and after each call (also the GPU studies' timer)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def proxy_row(shared: Path, name: str = "pretrained", repeats: int = REPEATS, n_frames: int = len(FRAMES),
              env: dict[str, str] | None = None) -> dict[str, Any]:
    """``name`` timed beside SGBM-HH (``beside_sgbm``, the path users get) in a child process run with ``env``
    (default :data:`AVX2_PROXY`) on the first ``n_frames`` bench frames: seconds, ratio and the instruction set
    torch ran at (``torch_capability``).

    Raises:
        RuntimeError: the child failed (its stderr's tail in the message).
    """
    cmd = [sys.executable, "-m", "pipelines.bench_models", "--proxy-child", name, "--shared", str(shared),
           "--repeats", str(repeats), "--frames", str(n_frames)]
    done = subprocess.run(cmd, env={**os.environ, **(AVX2_PROXY if env is None else env)}, capture_output=True,
                          text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"the AVX2-proxy timing of {name} failed (exit {done.returncode}): {done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _proxy_child(name: str, shared: Path, repeats: int, n_frames: int) -> dict[str, Any]:
    torch.set_num_threads(THREADS)
    model, frames, sgbm = load_model(name), _frames(shared)[:n_frames], _opencv(cv2.STEREO_SGBM_MODE_HH)
    row = beside_sgbm(model, frames, repeats, sgbm)
    full = beside_sgbm(model, frames, repeats, sgbm, run=float32_infer)
    return {"model": name, **row, "int8": fastpath.int8_encoder(model) is not None,
            "float32_s_per_frame": full["s_per_frame"], "float32_ratio": full["ratio"],
            "torch_capability": torch.backends.cpu.get_cpu_capability(),
            "env": {k: os.environ.get(k) for k in AVX2_PROXY}}


def _proxy_markdown(proxy: dict[str, Any] | None) -> list[str]:
    if proxy is None:
        return ["", "No AVX2-proxy row: this CPU has no AVX-512, so the rows above are an AVX2 machine's own."]
    target = TARGETS.get(proxy["model"])
    verdict = "" if target is None else f" (target <= {target}: {'met' if proxy['ratio'] <= target else 'not met'})"
    caps = " ".join(f"{k}={v}" for k, v in AVX2_PROXY.items())
    return ["", f"AVX2 proxy (the same frames in a child process with {caps}; torch at "
            f"{proxy['torch_capability']}): `{proxy['model']}` {proxy['s_per_frame']:.2f} s per frame, SGBM-HH "
            f"{proxy['sgbm_s']:.2f} s, **{proxy['ratio']:.2f}x**{verdict}"
            f"{' with its int8 encoder' if proxy.get('int8') else ''}; its float32 encoder "
            f"{proxy.get('float32_s_per_frame', float('nan')):.2f} s, {proxy.get('float32_ratio', float('nan')):.2f}x."]


def run(shared: Path) -> dict[str, Any]:
    torch.set_num_threads(THREADS)
    frames = _frames(shared)
    models = {name: load_model(name) for name in SHIPPED}
    rows = cpu_rows(models, frames)
    match = match_row(frames, _scored(shared))
    gpu = gpu_rows(models, *frames[0])
    proxy = proxy_row(shared) if "avx512f" in (cpuinfo_flags() or set()) else None
    results = {"avx2_proxy": proxy,
               "threads": THREADS, "repeats": REPEATS, "frames": [f"kitti15 {f}_10" for f in FRAMES], "cpu": rows,
               "match": match, "gpu": gpu, "load_avg": os.getloadavg()[0],
               "winograd_choices": fastpath.winograd_choices()}
    lines = [f"Each shipped model with its own settings, end to end (`infer`: resize, passes, filter), "
             f"{THREADS} threads, as `load_model` gives it (the engineered CPU pass: its encoder in int8 where the "
             f"weights have int8 clips and the CPU runs oneDNN's int8 convolution, its GRU convolutions Winograd or "
             f"direct, whichever this machine ran faster), the same with the encoder in float32, with Winograd "
             f"forced, with direct GRU convolutions forced and through the plain `OptStereo.forward`, beside OpenCV "
             f"SGBM-HH "
             f"(192 disparities) on the same {len(FRAMES)} KITTI 2015 "
             f"frames, alternating; median of {REPEATS} runs per frame (1 for a multi-pass model), ratio = median "
             "of the per-frame ratios.", "",
             "| model | int8 | s / KITTI frame | float32 s | Winograd s | no-Winograd s | plain s | OpenCV SGBM-HH s "
             "| x SGBM | float32 x SGBM | Winograd x SGBM | no-Winograd x SGBM | plain x SGBM | target | |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        lines.append(f"| `{r['model']}` | {'yes' if r['int8'] else 'no'} | {r['s_per_frame']:.2f} | "
                     f"{r['float32_s_per_frame']:.2f} | {r['winograd_s_per_frame']:.2f} | "
                     f"{r['direct_s_per_frame']:.2f} | {r['plain_s_per_frame']:.2f} | {r['sgbm_s']:.2f} | "
                     f"{r['ratio']:.2f} | {r['float32_ratio']:.2f} | {r['winograd_ratio']:.2f} | "
                     f"{r['direct_ratio']:.2f} | {r['plain_ratio']:.2f} | "
                     f"{'' if r['target'] is None else '<= ' + str(r['target'])} | {r['verdict'] or ''} |")
    lines.append(f"| `{match['model']}` | | {match['s_per_frame']:.2f} | | | | | {match['sgbm_s']:.2f} | "
                 f"{match['ratio']:.2f} | | | | | <= {match['target']} | {match['verdict'] or ''} |")
    choices = results["winograd_choices"]
    lines += ["", "The GRU convolutions this machine chose (True = Winograd): "
              + (", ".join(f"{k}: {v}" for k, v in choices.items()) or "none timed") + "."]
    lines += ["", f"`pvm-label match` = dense census SGM + row fill (`pvm_labeler.match.match_arrays`, numba on "
              f"{THREADS} threads, no network, file I/O not timed). bad-3 on the 15 KITTI 2015 GT frames, pooled: "
              f"{match['bad3']:.2f} % against SGBM-HH's {match['sgbm_bad3']:.2f} % with its holes filled alike "
              f"({match['bad3_ratio']:.2f}x)."]
    lines += _proxy_markdown(proxy)
    if gpu:
        lines += ["", f"GPU ({gpu[0]['device']}), end to end (uint8 numpy in, numpy out), synchronised, median of 10 "
                  "after 3 warm-up calls: `infer` (eager) and `GraphedPass` (the one-pass default captured as one "
                  "CUDA graph; issue 52's target for the default: <= 10 ms per KITTI frame on an H100):", "",
                  "| model | path | precision | ms / KITTI frame |", "|---|---|---|---:|"]
        lines += [f"| `{r['model']}` | {r['path']} | {r['precision']} | "
                  f"{r['error'] if r['ms'] is None else format(r['ms'], '.1f')} |" for r in gpu]
    return {"title": "Shipped models against OpenCV SGBM (issues 42, 52)", "results": results,
            "markdown": "\n".join(lines)}


def main(argv: list[str] | None = None) -> None:
    """The AVX2-proxy child (``proxy_row`` runs it): one JSON line on stdout."""
    parser = argparse.ArgumentParser(description="time one shipped model beside SGBM-HH (make bench's child)")
    parser.add_argument("--proxy-child", required=True, metavar="NAME")
    parser.add_argument("--shared", type=Path, default=Path("../shared/data"))
    parser.add_argument("--repeats", type=int, default=REPEATS)
    parser.add_argument("--frames", type=int, default=len(FRAMES))
    args = parser.parse_args(argv)
    print(json.dumps(_proxy_child(args.proxy_child, args.shared, args.repeats, args.frames)))


if __name__ == "__main__":
    main()
