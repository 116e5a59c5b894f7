"""The colour-weighted median post-filter (``refine: wmedian``) in torch, for inference on a GPU.

``pvm_labeler.refine.weighted_median`` (numba, the reference) filters a KITTI frame in about half a second on the
CPU: on a GPU, whose network pass takes a fraction of that, the filter would be most of the time per frame. This is
the same filter as tensor ops: every pixel that needs it (the same ``edge_pixels`` test) gathers its
(2r+1)^2 window, sorts the window's disparities, and takes the first whose cumulative colour weight reaches half the
total. It differs from the reference only by float32 summation order (the total weight is a tree sum here, a scan
there), which can move the half-weight crossing by one sorted value on rare pixels; tests bound that.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import torch
import torch.nn.functional as F

from pvm_labeler.refine import MedianParams, edge_pixels

#: Pixels filtered per batch: each holds (2r+1)^2 = 121 window values with their index, colours, weights and sort
#: order, ~50 bytes per value at the peak: ~0.4 GB of GPU memory per batch of 2^16.
CHUNK_PIXELS = 1 << 16


def weighted_median_torch(disp: npt.NDArray[np.float32], image: npt.NDArray[np.uint8],
                          params: MedianParams | None = None, device: torch.device | str = "cpu",
                          chunk_pixels: int = CHUNK_PIXELS) -> npt.NDArray[np.float32]:
    """Colour-weighted median of ``disp`` guided by ``image``, computed on ``device``.

    Args:
        disp: (H, W) float32 disparity, NaN = none (filled where a window has finite values).
        image: (H, W, 3) uint8 RGB of the same view.
        params: window radius, colour sigma, range threshold (``pvm_labeler.refine.MedianParams``; None: its
            defaults, the shipped filter's).
        device: where the windows are sorted (a CUDA device is what this is for).
        chunk_pixels: pixels per batch (bounds the memory: ~chunk_pixels x (2r+1)^2 x 50 bytes).

    Returns:
        (H, W) float32 refined disparity; each output is one of the input values of its window.
    """
    if disp.ndim != 2 or image.ndim != 3 or image.shape[:2] != disp.shape:
        raise ValueError(f"weighted_median_torch: disparity {disp.shape} and image {image.shape} do not match")
    params = params or MedianParams()
    disp = np.ascontiguousarray(disp, dtype=np.float32)
    todo = np.flatnonzero(edge_pixels(disp, params.radius, params.min_range))
    out = disp.copy()
    if todo.size == 0:
        return out
    r, (height, width) = params.radius, disp.shape
    dev = torch.device(device)
    # NaN padding: a window clipped at the border sees no value there, as in the reference kernel
    values = F.pad(torch.from_numpy(disp).to(dev)[None, None], (r, r, r, r), value=float("nan")).reshape(-1)
    guide = F.pad(torch.from_numpy(np.ascontiguousarray(image)).to(dev).permute(2, 0, 1).float(), (r, r, r, r))
    guide = guide.reshape(3, -1)
    padded_width = width + 2 * r
    offsets = torch.arange(-r, r + 1, device=dev)
    window_offsets = (offsets[:, None] * padded_width + offsets[None, :]).reshape(-1, 1)  # (K, 1) flat offsets
    inv_two_sigma2 = torch.tensor(1.0 / (2.0 * params.sigma**2), dtype=torch.float32, device=dev)
    result = torch.from_numpy(out).to(dev).reshape(-1)
    for start in range(0, todo.size, chunk_pixels):
        flat = torch.from_numpy(todo[start:start + chunk_pixels]).to(dev)
        centre = (flat // width + r) * padded_width + flat % width + r  # (N,) in the padded maps
        where = centre[None] + window_offsets  # (K, N), K = (2r+1)^2
        window = values[where]
        diff = guide[:, where] - guide[:, centre][:, None]  # (3, K, N)
        finite = torch.isfinite(window)
        weight = torch.exp(-(diff * diff).sum(0) * inv_two_sigma2).masked_fill(~finite, 0.0)
        ordered, order = torch.sort(window.nan_to_num(nan=float("inf")), dim=0, stable=True)  # NaN last
        cumulative = torch.cumsum(torch.gather(weight, 0, order), dim=0)
        first = torch.argmax((cumulative >= weight.sum(0) * 0.5).to(torch.uint8), dim=0)  # the first crossing
        median = torch.gather(ordered, 0, first[None])[0]
        keep = finite.any(0)  # a window without a finite value keeps its input
        result[flat[keep]] = median[keep]
    return result.reshape(height, width).cpu().numpy()
