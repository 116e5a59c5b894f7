"""Peak-memory estimate of one inference, checked against the free memory before a large pair is decoded.

Measured once (issue 45) with the model shipped then (version 14: input scale 1.625, three passes, wmedian;
``optstereo-predict --checkpoint pretrained``, float32) on blurred random-texture pairs, on a 16-core x86 machine
with an H100:

| pair (H x W)  | pixels the network sees (x 1.625^2) | CPU peak RSS of the process | CUDA peak allocated |
| ------------- | ----------------------------------- | --------------------------- | ------------------- |
| 375 x 1242    | 1.23 MP                             | 1.18 GB                     | 1.02 GiB            |
| 1500 x 2000   | 7.9 MP                              | 3.87 GB                     |                     |
| 3000 x 4000   | 31.7 MP                             | 13.3 GB                     | 25.0 GiB            |

Both grow linearly with the pixels the NETWORK sees (the pair's pixels x scale^2): the CPU's by 0.40 GB per megapixel
above a 0.7 GB base, the GPU's by 0.80 GiB per megapixel. The lines were first fitted per pixel of the pair
(1.06 GB and 2.1 GiB per megapixel) and then multiplied by scale^2 again, which counted the measurement's own
1.625^2 = 2.64 twice (issue 51). Version 15 (scale 1, one pass) confirms the CPU line on a 2-core x86 machine (2
threads): 0.57 GB at 375 x 1242, 0.99 GB at 1000 x 1500 (0.41 GB per megapixel), and version 14 there gives 1.03 GB
at 375 x 1242 (fewer threads than the 16 above). The CUDA line is the same correction of the H100 figures, not
measured again. :func:`estimate_peak_bytes` uses these lines; the base covers the 16-thread, wmedian, three-pass
case, so the estimate errs on the side of refusing (``tests/test_bad_input_optstereo.py`` checks a measured peak).
"""

from __future__ import annotations

from pathlib import Path

import torch

#: 1.06 GB and 2.1 GiB per megapixel of the pair measured at input scale 1.625 (see above), per pixel the network sees
MEASURED_SCALE = 1.625
CPU_BASE_BYTES = 0.70e9
CPU_BYTES_PER_PIXEL = 1060.0 / MEASURED_SCALE**2  # ~401
CUDA_BASE_BYTES = 0.05 * 2**30
CUDA_BYTES_PER_PIXEL = 2.1 * 2**30 / 1e6 / MEASURED_SCALE**2  # ~0.80 GiB per megapixel


def estimate_peak_bytes(height: int, width: int, scale: float = 1.0, cuda: bool = False) -> float:
    """Estimated peak memory (bytes) of one inference on an (H, W) pair run at input ``scale`` (CPU RSS or CUDA): a
    base plus a cost per pixel the network sees (H x W x scale^2)."""
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
