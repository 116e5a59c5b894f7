"""`make bench` section "labeler": our numba SGM vs OpenCV StereoSGBM, and one full PVM label split into stages.

Setup (issue 2, "Speed"): KITTI 2015 frame 000000 (1242x375) from ../shared/data, max_disp = 192, ONE thread for
numba and OpenCV. All variants are timed round-robin in the same process (so a noisy, shared CPU affects them
alike) and reported as medians of >= 5 runs after a warm-up; the JIT compile time is measured separately in a
fresh process with an empty numba cache. Ratios are ours / OpenCV; cells/s = pixels x disparities x paths / s.

Run alone: ``.venv/bin/python -m pipelines.bench --only labeler --out /tmp/bench_a1``.
"""

from __future__ import annotations

import logging
import os
import statistics
import subprocess
import sys
import tempfile
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numba
import numpy as np

from pvm_labeler.config import LabelerConfig
from pvm_labeler.kernels._lanes import SENTINEL16, path_lanes
from pvm_labeler.kernels.aggregate import aggregate_backward_wta, aggregate_forward
from pvm_labeler.kernels.cost import census_dtype, census_transform, cost_volume, cost_volume_right
from pvm_labeler.multiscale import label_pair
from pvm_labeler.parallel import thread_budget
from pvm_labeler.sgm import release_workspace, sgm_pair

logger = logging.getLogger(__name__)

FRAME = "000000"
MAX_DISP = 192
REPEATS = 7
TARGET_VS_HH = 0.25
TARGET_VS_SGBM = 1.0

_COMPILE_SNIPPET = """
import time, numpy as np
from pvm_labeler.config import LabelerConfig
from pvm_labeler.sgm import release_workspace, sgm_pair
rng = np.random.default_rng(0)
img = rng.integers(0, 256, (32, 64), dtype=np.uint8)
t0 = time.perf_counter()
sgm_pair(img, img, LabelerConfig(max_disp=16))
print(time.perf_counter() - t0)
"""


def _load(shared: Path) -> tuple[np.ndarray, np.ndarray]:
    root = shared / "kitti15" / "training"
    left = cv2.imread(str(root / "image_2" / f"{FRAME}_10.png"), cv2.IMREAD_COLOR_RGB)
    right = cv2.imread(str(root / "image_3" / f"{FRAME}_10.png"), cv2.IMREAD_COLOR_RGB)
    if left is None or right is None:
        raise FileNotFoundError(f"KITTI 2015 frame {FRAME} not found under {root}")
    return left, right


def _opencv(mode: int) -> Any:
    # blockSize 5 matches our 5x5 census window; P1/P2 are OpenCV's usual 8 / 32 x blockSize^2 (uint8 BT costs).
    block = 5
    return cv2.StereoSGBM_create(minDisparity=0, numDisparities=MAX_DISP, blockSize=block, P1=8 * block * block,
                                 P2=32 * block * block, mode=mode)


def _opencv_pair(matcher: Any, left: np.ndarray, right: np.ndarray) -> None:
    """Left view, then the right view by the flip trick (flipped, swapped pair)."""
    matcher.compute(left, right)
    flipped = matcher.compute(np.ascontiguousarray(right[:, ::-1]), np.ascontiguousarray(left[:, ::-1]))
    assert flipped.shape == left.shape


def _round_robin(cases: dict[str, Callable[[], Any]], repeats: int) -> tuple[dict[str, list[float]],
                                                                               dict[str, list[float]]]:
    """Wall and CPU (process_time) seconds of each case, ``repeats`` rounds after one warm-up round.

    CPU time is recorded too because on an oversubscribed machine (load average > cores) wall time mostly measures
    how long the process waited for a core; every case here runs on one thread, so CPU time is comparable.
    """
    for fn in cases.values():  # warm-up (JIT compile / cache load, OpenCV buffers)
        fn()
    wall: dict[str, list[float]] = {name: [] for name in cases}
    cpu: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(repeats):
        for name, fn in cases.items():
            c0 = time.process_time()
            t0 = time.perf_counter()
            fn()
            wall[name].append(time.perf_counter() - t0)
            cpu[name].append(time.process_time() - c0)
    return wall, cpu


def _sgm_stages(grey_l: np.ndarray, grey_r: np.ndarray, cfg: LabelerConfig, repeats: int) -> dict[str, float]:
    """Median CPU seconds of each kernel of sgm_pair (both views), called exactly as sgm.py calls them."""
    height, width = grey_l.shape
    c_max = cfg.census_window**2 - 1
    cen_l = np.empty((height, width), census_dtype(cfg.census_window))
    cen_r = np.empty_like(cen_l)
    cost = np.empty((height, width, MAX_DISP), np.uint8)
    cost_r = np.empty_like(cost)
    s_buf = np.empty((height, width, MAX_DISP), np.uint16)
    lanes = path_lanes(c_max, cfg.p1, cfg.p2)
    maps = [np.empty((height, width), np.float32) for _ in range(3)]

    def census() -> None:
        census_transform(grey_l, cfg.census_window, cen_l)
        census_transform(grey_r, cfg.census_window, cen_r)

    stages = {
        "census (both)": census,
        "cost volume": lambda: cost_volume(cen_l, cen_r, c_max, cost, MAX_DISP, 0),
        "forward sweep (4 paths)": lambda: aggregate_forward(cost, grey_l, cfg.p1, cfg.p2, cfg.p2_adaptive, True,
                                                             s_buf, *lanes),
        "backward sweep (4 paths) + WTA": lambda: aggregate_backward_wta(
            cost, grey_l, cfg.p1, cfg.p2, cfg.p2_adaptive, True, s_buf, False, float(8 * c_max), MAX_DISP,
            *maps, *lanes, False),  # no uniqueness pass, as sgm_pair's default
        # the same sweeps forced to uint16 path costs: what the uint8 lanes buy (same results, tested)
        "forward sweep, uint16 lanes (not used)": lambda: aggregate_forward(
            cost, grey_l, cfg.p1, cfg.p2, cfg.p2_adaptive, True, s_buf, np.uint16, SENTINEL16),
        "backward sweep + WTA, uint16 lanes (not used)": lambda: aggregate_backward_wta(
            cost, grey_l, cfg.p1, cfg.p2, cfg.p2_adaptive, True, s_buf, False, float(8 * c_max), MAX_DISP,
            *maps, np.uint16, SENTINEL16, False),
        "right cost from the shared census (used)": lambda: cost_volume_right(cen_l, cen_r, c_max, cost_r, MAX_DISP,
                                                                              0),
    }
    _, cpu = _round_robin(stages, repeats)
    return {name: statistics.median(ts) for name, ts in cpu.items()}


def _peak_mb(fn: Callable[[], Any]) -> float:
    """Peak of NumPy allocations during fn (tracemalloc sees every ndarray buffer; numba scratch is < 5 MB).

    The SGM scratch arena is released first so that its allocation is counted (it is reused across calls).
    """
    release_workspace()
    tracemalloc.start()
    tracemalloc.reset_peak()
    fn()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak / 2**20


def _compile_seconds() -> float | None:
    """First sgm_pair call in a fresh interpreter with an empty numba cache (= pure JIT compile time)."""
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache, NUMBA_NUM_THREADS="1")
        try:
            out = subprocess.run([sys.executable, "-c", _COMPILE_SNIPPET], env=env, capture_output=True, text=True,
                                 check=True, timeout=900)
        except (subprocess.SubprocessError, OSError) as exc:
            logger.warning("compile-time measurement failed: %s", exc)
            return None
    return float(out.stdout.strip().splitlines()[-1])


def _full_label(left: np.ndarray, right: np.ndarray, repeats: int) -> dict[str, Any]:
    cfg = LabelerConfig()
    runs, peak = _label_runs(label_pair, left, right, cfg, repeats)
    # The same frame with a budget of 2 threads: the views of every SGM pair side by side (parallel.run_two).
    with thread_budget(2):
        runs2, peak2 = _label_runs(label_pair, left, right, cfg, repeats)
    stages = {key: statistics.median(r[key] for r in runs) for key in runs[0]}
    two = {"wall_s": statistics.median(r["wall"] for r in runs2), "cpu_s": statistics.median(r["cpu"] for r in runs2),
           "peak_mb": peak2}
    return {"k": cfg.k, "repeats": repeats, "stages_s": stages, "peak_mb": peak, "two_threads": two}


def _label_runs(label_pair: Callable[..., Any], left: np.ndarray, right: np.ndarray, cfg: LabelerConfig,
                repeats: int) -> tuple[list[dict[str, float]], float]:
    """A warm-up call (it also allocates the SGM arenas), ``repeats`` timed calls (LabelResult.timings plus wall and
    cpu seconds each), then the peak NumPy memory of one more call."""
    label_pair(left, right, cfg, FRAME)
    runs = []
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        res = label_pair(left, right, cfg, FRAME)
        wall = time.perf_counter() - t0
        runs.append(dict(res.timings, wall=wall, cpu=time.process_time() - c0))
    return runs, _peak_mb(lambda: label_pair(left, right, cfg, FRAME))


def _markdown(res: dict[str, Any]) -> str:
    med = res["median_s"]
    cells = res["cells_per_s"]
    lines = [
        f"KITTI 2015 frame {FRAME} ({res['width']}x{res['height']}), max_disp={MAX_DISP}, 1 thread (numba and "
        f"OpenCV), median of {res['repeats']} runs after warm-up, round-robin in one process; "
        f"load average at start {res['loadavg_start']:.1f} (the CPU is shared, so absolute times are noisy; "
        "compare the ratios).",
        "",
        "Times are CPU seconds (process_time) of the single-threaded call; wall-clock medians are in the JSON and the "
        "last column.",
        "",
        "| method | paths | median CPU ms | cells/s (G) | ours / this (CPU) | median wall ms |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    paths = {"ours left": 8, "ours left+right": 8, "OpenCV HH left": 8, "OpenCV SGBM left": 5,
             "OpenCV HH left+right (flip)": 8, "OpenCV SGBM left+right (flip)": 5}
    for name, n_paths in paths.items():
        ours = med["ours left+right"] if "right" in name else med["ours left"]
        ratio = "" if name.startswith("ours") else f"{ours / med[name]:.2f}"
        lines.append(f"| {name} | {n_paths} | {med[name] * 1e3:.0f} | {cells[name] / 1e9:.2f} | {ratio} | "
                     f"{res['median_wall_s'][name] * 1e3:.0f} |")
    r = res["ratios"]
    lines += [
        "",
        f"Targets: ours left <= {TARGET_VS_HH} x HH (measured {r['left_vs_hh']:.2f}, "
        f"{'met' if r['left_vs_hh'] <= TARGET_VS_HH else 'NOT met'}); <= {TARGET_VS_SGBM} x SGBM (measured "
        f"{r['left_vs_sgbm']:.2f}, {'met' if r['left_vs_sgbm'] <= TARGET_VS_SGBM else 'NOT met'}).",
        f"JIT compile of sgm_pair (fresh process, empty cache): {res['compile_s']:.1f} s"
        if res["compile_s"] is not None else "JIT compile: not measured",
        f"Peak NumPy memory: SGM left {res['peak_mb']['ours left']:.0f} MB, SGM left+right "
        f"{res['peak_mb']['ours left+right']:.0f} MB.",
        "",
        "Our SGM stages (both views; median CPU ms):",
        "",
        "| stage | ms |",
        "| --- | --- |",
    ]
    lines += [f"| {name} | {sec * 1e3:.0f} |" for name, sec in res["sgm_stages_s"].items()]
    full = res["full_label"]
    lines.append("")
    if "stages_s" in full:
        lines += [f"Full PVM label (K={full['k']}, both views, voting, LRDCC), median of {full['repeats']} runs, "
                  f"peak NumPy memory {full['peak_mb']:.0f} MB (stages: wall ms from LabelResult.timings; 'cpu' is "
                  "the CPU time of the whole call):", "", "| stage | ms |", "| --- | --- |"]
        lines += [f"| {name} | {sec * 1e3:.0f} |" for name, sec in full["stages_s"].items()]
        two = full.get("two_threads")
        if two:
            lines += ["", f"Same frame with 2 threads (the two views of every SGM pair side by side, "
                      f"parallel.run_two): wall {two['wall_s'] * 1e3:.0f} ms = "
                      f"{full['stages_s']['wall'] / two['wall_s']:.2f}x faster than 1 thread, CPU "
                      f"{two['cpu_s'] * 1e3:.0f} ms, peak NumPy memory {two['peak_mb']:.0f} MB."]
    else:
        lines.append(f"Full PVM label: {full['note']}")
    return "\n".join(lines)


def run(shared: Path, repeats: int = REPEATS) -> dict[str, Any]:
    """Run the section; returns {"title", "results", "markdown"} for pipelines/bench.py."""
    old_threads = numba.get_num_threads()
    old_cv_threads = cv2.getNumThreads()
    numba.set_num_threads(1)
    cv2.setNumThreads(1)
    try:
        left, right = _load(shared)
        grey_l = np.ascontiguousarray(cv2.cvtColor(left, cv2.COLOR_RGB2GRAY))
        grey_r = np.ascontiguousarray(cv2.cvtColor(right, cv2.COLOR_RGB2GRAY))
        height, width = grey_l.shape
        cfg = LabelerConfig(max_disp=MAX_DISP)
        loadavg = os.getloadavg()[0]
        hh = _opencv(cv2.STEREO_SGBM_MODE_HH)
        sgbm = _opencv(cv2.STEREO_SGBM_MODE_SGBM)
        cases = {
            "ours left": lambda: sgm_pair(grey_l, grey_r, cfg, right_view=False),
            "ours left+right": lambda: sgm_pair(grey_l, grey_r, cfg),
            "OpenCV HH left": lambda: hh.compute(grey_l, grey_r),
            "OpenCV SGBM left": lambda: sgbm.compute(grey_l, grey_r),
            "OpenCV HH left+right (flip)": lambda: _opencv_pair(hh, grey_l, grey_r),
            "OpenCV SGBM left+right (flip)": lambda: _opencv_pair(sgbm, grey_l, grey_r),
        }
        logger.info("timing SGM variants (%d rounds)", repeats)
        wall, cpu = _round_robin(cases, repeats)
        median = {name: statistics.median(ts) for name, ts in cpu.items()}
        median_wall = {name: statistics.median(ts) for name, ts in wall.items()}
        n_paths = {"ours left": 8, "ours left+right": 16, "OpenCV HH left": 8, "OpenCV SGBM left": 5,
                   "OpenCV HH left+right (flip)": 16, "OpenCV SGBM left+right (flip)": 10}
        cells = {name: height * width * MAX_DISP * n_paths[name] / median[name] for name in median}
        results: dict[str, Any] = {
            "frame": FRAME, "height": height, "width": width, "max_disp": MAX_DISP, "repeats": repeats,
            "threads": 1, "loadavg_start": loadavg, "runs_wall_s": wall, "runs_cpu_s": cpu, "median_s": median,
            "median_wall_s": median_wall, "cells_per_s": cells,
            "ratios": {
                "left_vs_hh": median["ours left"] / median["OpenCV HH left"],
                "left_vs_sgbm": median["ours left"] / median["OpenCV SGBM left"],
                "pair_vs_hh_flip": median["ours left+right"] / median["OpenCV HH left+right (flip)"],
                "pair_vs_sgbm_flip": median["ours left+right"] / median["OpenCV SGBM left+right (flip)"],
            },
            "targets": {"left_vs_hh": TARGET_VS_HH, "left_vs_sgbm": TARGET_VS_SGBM},
        }
        results["peak_mb"] = {"ours left": _peak_mb(cases["ours left"]),
                              "ours left+right": _peak_mb(cases["ours left+right"])}
        logger.info("timing SGM stages")
        results["sgm_stages_s"] = _sgm_stages(grey_l, grey_r, cfg, repeats)
        logger.info("timing the full PVM label")
        results["full_label"] = _full_label(left, right, max(5, repeats // 2))
        results["loadavg_end"] = os.getloadavg()[0]
        logger.info("measuring the JIT compile time in a fresh process")
        results["compile_s"] = _compile_seconds()
    finally:
        numba.set_num_threads(old_threads)
        cv2.setNumThreads(old_cv_threads)
    return {"title": "Labeler: numba SGM vs OpenCV StereoSGBM, full PVM frame", "results": results,
            "markdown": _markdown(results)}
