"""Peak-memory estimate of one inference, checked against the free memory before a large pair is decoded.

Measured once (issue 45) with the shipped model (``optstereo-predict --checkpoint pretrained``, float32, default
scale and refinement) on blurred random-texture pairs, on a 16-core x86 machine with an H100:

| pair (H x W)  | CPU peak RSS of the process | CUDA peak allocated |
| ------------- | --------------------------- | ------------------- |
| 375 x 1242    | 1.18 GB                     | 1.02 GiB            |
| 1500 x 2000   | 3.87 GB                     |                     |
| 3000 x 4000   | 13.3 GB                     | 25.0 GiB            |

Both grow linearly with the pixels the network sees: the CPU's by 1.06 GB per megapixel above a 0.7 GB base, the
GPU's by 2.1 GiB per megapixel. :func:`estimate_peak_bytes` uses these lines; smaller models need less, so the
estimate errs on the side of refusing.
"""

from __future__ import annotations

from pathlib import Path

import torch

CPU_BASE_BYTES = 0.70e9
CPU_BYTES_PER_PIXEL = 1060.0
CUDA_BASE_BYTES = 0.05 * 2**30
CUDA_BYTES_PER_PIXEL = 2.1 * 2**30 / 1e6


def estimate_peak_bytes(height: int, width: int, scale: float = 1.0, cuda: bool = False) -> float:
    """Estimated peak memory (bytes) of one inference on an (H, W) pair run at input ``scale`` (CPU RSS or CUDA)."""
    pixels = height * width * max(scale, 0.0) ** 2
    if cuda:
        return CUDA_BASE_BYTES + CUDA_BYTES_PER_PIXEL * pixels
    return CPU_BASE_BYTES + CPU_BYTES_PER_PIXEL * pixels


def available_bytes(meminfo: Path = Path("/proc/meminfo"), cgroup: Path = Path("/sys/fs/cgroup")) -> float | None:
    """Memory this process can still take: MemAvailable, lowered to the cgroup v2 limit's headroom; None = unknown."""
    found: list[float] = []
    try:
        for line in meminfo.read_text().splitlines():
            if line.startswith("MemAvailable:"):
                found.append(float(line.split()[1]) * 1024)
    except OSError:
        pass
    try:
        limit = (cgroup / "memory.max").read_text().strip()
        if limit != "max":
            found.append(float(limit) - float((cgroup / "memory.current").read_text()))
    except (OSError, ValueError):
        pass
    return min(found) if found else None


def check_fits(what: str, height: int, width: int, scale: float = 1.0, cuda: bool = False,
               available: float | None = None) -> None:
    """Raise MemoryError naming ``what`` when the estimated peak exceeds the free memory (``available``, bytes).

    ``available`` None asks the system (:func:`available_bytes`, or the GPU's free memory with ``cuda``); an
    unknown amount is never refused.
    """
    need = estimate_peak_bytes(height, width, scale, cuda)
    if available is None:
        available = _cuda_free() if cuda else available_bytes()
    if available is None or need <= available:
        return
    where = "GPU" if cuda else "RAM"
    fit = (available / need) ** 0.5 * scale
    raise MemoryError(f"{what}: a {height} x {width} pair at input scale {scale:g} needs about {need / 1e9:.1f} GB "
                      f"of {where}, {available / 1e9:.1f} GB is free; refused before decoding it. Give --scale "
                      f"{max(0.05, int(fit * 20) / 20):g} or smaller (or free memory)")


def _cuda_free() -> float | None:
    return float(torch.cuda.mem_get_info()[0]) if torch.cuda.is_available() else None
