"""Pictures: colour disparity maps, KITTI-style error maps, density-vs-error plots (matplotlib Agg, no display)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

#: KITTI devkit error colours (disp_error_image): bins of the normalised error min(e / 3 px, (e / |gt|) / 5 %),
#: from dark blue (tiny error) to dark red (> 16x the outlier threshold). Values are RGB.
KITTI_ERROR_BINS: tuple[tuple[float, float, tuple[int, int, int]], ...] = (
    (0 / 3.0, 0.1875 / 3.0, (49, 54, 149)),
    (0.1875 / 3.0, 0.375 / 3.0, (69, 117, 180)),
    (0.375 / 3.0, 0.75 / 3.0, (116, 173, 209)),
    (0.75 / 3.0, 1.5 / 3.0, (171, 217, 233)),
    (1.5 / 3.0, 3 / 3.0, (224, 243, 248)),
    (3 / 3.0, 6 / 3.0, (254, 224, 144)),
    (6 / 3.0, 12 / 3.0, (253, 174, 97)),
    (12 / 3.0, 24 / 3.0, (244, 109, 67)),
    (24 / 3.0, 48 / 3.0, (215, 48, 39)),
    (48 / 3.0, np.inf, (165, 0, 38)),
)
NO_LABEL_RGB = (70, 70, 70)  # GT known but nothing predicted: dark grey, so coverage holes stay visible


def colorize_disparity(
    disp: npt.ArrayLike, max_disp: float | None = None, colormap: int = cv2.COLORMAP_TURBO
) -> npt.NDArray[np.uint8]:
    """Colour rendering of a disparity map; NaN/inf (no disparity) are black.

    Args:
        disp: (H, W) float disparity.
        max_disp: value mapped to the top colour (default: the map's finite maximum).
        colormap: OpenCV colormap id (turbo: perceptually ordered, near = red).

    Returns:
        (H, W, 3) uint8 RGB.
    """
    disp = np.asarray(disp, dtype=np.float32)
    finite = np.isfinite(disp)
    vmax = float(max_disp) if max_disp else (float(disp[finite].max()) if finite.any() else 1.0)
    grey = np.clip(np.where(finite, disp, 0) / max(vmax, 1e-6) * 255.0, 0, 255).astype(np.uint8)
    out = cv2.applyColorMap(grey, colormap)[..., ::-1].copy()
    out[~finite] = 0
    return out


def error_map(
    pred: npt.ArrayLike, gt: npt.ArrayLike, tau: tuple[float, float] = (3.0, 0.05), dilate: int = 0
) -> npt.NDArray[np.uint8]:
    """KITTI-style disparity error picture.

    Colour = bin of min(|pred - gt| / tau[0], (|pred - gt| / |gt|) / tau[1]) (blue good ... red outlier, the
    devkit's palette); black where there is no GT; dark grey where GT exists but pred has no value.

    Args:
        pred: (H, W) float, NaN = not predicted.
        gt: (H, W) float, NaN = unknown.
        tau: KITTI outlier thresholds (3 px, 5 %).
        dilate: grow each coloured pixel by this many pixels (sparse LiDAR GT is hard to see otherwise).

    Returns:
        (H, W, 3) uint8 RGB.
    """
    pred = np.asarray(pred, dtype=np.float32)
    gt = np.asarray(gt, dtype=np.float32)
    has_gt = np.isfinite(gt)
    covered = has_gt & np.isfinite(pred)
    with np.errstate(invalid="ignore", divide="ignore"):
        err = np.abs(pred - gt)
        norm = np.minimum(err / tau[0], err / np.maximum(np.abs(gt), 1e-6) / tau[1])
    out = np.zeros((*gt.shape, 3), np.uint8)
    out[has_gt & ~covered] = NO_LABEL_RGB
    for low, high, rgb in KITTI_ERROR_BINS:
        out[covered & (norm >= low) & (norm < high)] = rgb
    if dilate > 0:
        kernel = np.ones((2 * dilate + 1, 2 * dilate + 1), np.uint8)
        grown = cv2.dilate(out, kernel)
        out = np.where(has_gt[..., None], out, grown)
    return out


LEGEND_HEIGHT = 40  # px of the strip a legend adds below a picture: colours, numbers, a line of words


def _text(strip: npt.NDArray[np.uint8], text: str, x: int, y: int, rgb: tuple[int, int, int] = (255, 255, 255)
          ) -> None:
    """Small Hershey text drawn into the (h, w, 3) uint8 RGB ``strip`` in place, its left end at x (kept inside); a
    line wider than the strip is drawn smaller to fit (its start fell off the left edge of a narrow picture)."""
    font_scale = 0.35
    (w, _), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, font_scale, 1)
    while w > strip.shape[1] - 4 and font_scale > 0.15:  # from x = 2, a pixel of antialiasing to spare; Hershey
        font_scale *= 0.9  # sizes come in steps, so shrink until it fits
        (w, _), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, font_scale, 1)
    cv2.putText(strip, text, (int(max(1, min(x, strip.shape[1] - w - 1))), y), cv2.FONT_HERSHEY_SIMPLEX, font_scale,
                rgb, 1, cv2.LINE_AA)


def disparity_legend(width: int, max_disp: float, colormap: int = cv2.COLORMAP_TURBO,
                     above: float = 0.0) -> npt.NDArray[np.uint8]:
    """(LEGEND_HEIGHT, width, 3) uint8 RGB strip: the colour ramp of :func:`colorize_disparity` from 0 to
    ``max_disp`` px, ticks at 0, a half and the top, and "black: no disparity". ``above``: the fraction of the
    picture's values beyond ``max_disp`` (drawn in the top colour): the top tick then reads ">=" and the line says
    how many."""
    strip = np.zeros((LEGEND_HEIGHT, width, 3), np.uint8)
    ramp = np.linspace(0, 255, width).astype(np.uint8)[None, :]
    strip[:12] = cv2.applyColorMap(np.repeat(ramp, 12, axis=0), colormap)[..., ::-1]
    for frac in (0.0, 0.5, 1.0):
        mark = ">=" if frac == 1.0 and above > 0 else ""
        _text(strip, f"{mark}{frac * max_disp:.3g} px", int(frac * width) - (0 if frac == 0 else 24 + 8 * len(mark)),
              24)
    more = f"; {above:.1%} of it beyond the scale, in its top colour" if above > 0 else ""
    _text(strip, f"disparity; black: none{more}", 2, 37, (160, 160, 160))
    return strip


def error_legend(width: int, tau: tuple[float, float] = (3.0, 0.05), reference: str = "GT") -> npt.NDArray[np.uint8]:
    """(LEGEND_HEIGHT, width, 3) uint8 RGB strip: :func:`error_map`'s ten bins side by side, each under its lower
    bound in px. A pixel's bin is that of min(error / tau[0], error / (tau[1] x its ``reference`` disparity)) (the
    KITTI devkit's rule), so where the reference exceeds tau[0] / tau[1] (60 px) every bound grows by reference /
    60 px. Grey = no prediction, black = no ``reference`` (GT, or a GT-free set's PVM label)."""
    strip = np.zeros((LEGEND_HEIGHT, width, 3), np.uint8)
    step = width / len(KITTI_ERROR_BINS)
    for i, (low, _, rgb) in enumerate(KITTI_ERROR_BINS):
        strip[:12, int(i * step):int((i + 1) * step)] = rgb
        _text(strip, f"{low * tau[0]:.2g}", int(i * step) + 2, 24)
    knee = tau[0] / tau[1]
    _text(strip, f"error in px (bounds x {reference}/{knee:.0f} px where {reference} > {knee:.0f} px); grey: no "
          f"prediction, black: no {reference}", 2, 37, (160, 160, 160))
    return strip


def with_legend(picture: npt.NDArray[np.uint8], legend: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    """The (H, W, 3) uint8 ``picture`` with the (h, W, 3) ``legend`` strip below it: (H + h, W, 3)."""
    return np.concatenate([picture, legend], axis=0)


def density_error_plot(
    runs: Sequence[dict[str, Any]],
    path: Path | str,
    x: str = "density",
    ys: Sequence[str] = ("bad3", "epe"),
    title: str = "PVM labels: density vs error",
    baselines: Sequence[dict[str, Any]] = (),
) -> Path:
    """Plot error vs label density for several runs (e.g. a kappa sweep), one panel per error metric.

    Args:
        runs: dicts with ``name`` and the metric keys (``density`` %, ``bad3`` %, ``epe`` px ...); drawn as one
            connected curve in the given order, each point labelled with its name.
        path: PNG file to write.
        x: metric on the x axis.
        ys: metrics on the y axes (one subplot each).
        title: figure title.
        baselines: optional further curves: dicts with ``name`` and ``points`` (a list of metric dicts).

    Returns:
        The written path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = {"density": "label density (% of GT-valid px)", "bad3": "bad-3 (%)", "bad1": "bad-1 (%)",
              "bad2": "bad-2 (%)", "epe": "AEPE (px)", "d1": "D1 (%)"}
    fig, axes = plt.subplots(1, len(ys), figsize=(5.5 * len(ys), 4.2), squeeze=False)
    for ax, y in zip(axes[0], ys, strict=True):
        xs = [r[x] for r in runs]
        vals = [r[y] for r in runs]
        ax.plot(xs, vals, "o-", color="tab:blue", label="PVM")
        for r in runs:
            ax.annotate(str(r["name"]), (r[x], r[y]), fontsize=7, xytext=(3, 3), textcoords="offset points")
        for base in baselines:
            pts = base["points"]
            ax.plot([p[x] for p in pts], [p[y] for p in pts], "s--", label=base["name"])
        ax.set_xlabel(labels.get(x, x))
        ax.set_ylabel(labels.get(y, y))
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
