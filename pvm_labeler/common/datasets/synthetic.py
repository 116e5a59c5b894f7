"""The embedded `sample` dataset: scikit-image's motorcycle pair and deterministic synthetic layered scenes."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pvm_labeler.common.datasets.refs import PairRef

# ------------------------------------------------------------------------------------------------------ sample
#: (height, width, seed) of the synthetic layered scenes in the `sample` dataset. Sizes differ on purpose so
#: consumers cannot assume one shape per shard.
SYNTHETIC_SCENES: tuple[tuple[int, int, int], ...] = ((240, 320, 0), (224, 336, 1), (256, 304, 2))
_SYNTHETIC_MARK = "<synthetic>"


def _discover_sample(
    root: Path | None, split: str, synthetic: bool | str = True, motorcycle: bool | str = True, **_: Any
) -> list[PairRef]:
    import skimage

    data_dir = Path(skimage.__file__).parent / "data"
    refs = []
    if _flag(motorcycle):
        refs.append(
            PairRef(
                frame_id="motorcycle",
                left=data_dir / "motorcycle_left.png",
                right=data_dir / "motorcycle_right.png",
                gt=data_dir / "motorcycle_disp.npz",
                meta={"dataset": "sample", "gt_format": "skimage_npz"},
            )
        )
    if _flag(synthetic):
        for i, (height, width, seed) in enumerate(SYNTHETIC_SCENES):
            fake = Path(_SYNTHETIC_MARK) / f"synthetic-{i:03d}"
            refs.append(
                PairRef(
                    frame_id=f"synthetic-{i:03d}",
                    left=fake / "left",
                    right=fake / "right",
                    gt=fake / "gt",
                    gt_noc=fake / "gt_noc",
                    gt_right=fake / "gt_right",
                    meta={"dataset": "sample", "synthetic": [height, width, seed]},
                )
            )
    return refs


def _flag(value: bool | str) -> bool:
    """Reader options may come from YAML/CLI as strings."""
    return value if isinstance(value, bool) else str(value).lower() not in ("0", "false", "no", "off")


def _smooth_texture(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """Random texture with energy at several scales so every pyramid level has something to match."""
    import cv2

    tex = np.zeros((height, width), np.float32)
    for sigma, weight in ((0.7, 0.5), (2.0, 0.3), (6.0, 0.2)):
        noise = rng.standard_normal((height, width)).astype(np.float32)
        blurred = cv2.GaussianBlur(noise, (0, 0), sigma)
        tex += weight * blurred / (blurred.std() + 1e-6)
    rgb = np.stack([tex, np.roll(tex, 3, axis=1), np.roll(tex, 5, axis=0)], axis=2)
    return np.clip(128 + 40 * rgb, 0, 255).astype(np.float32)


def make_layered_scene(height: int, width: int, seed: int) -> dict[str, np.ndarray]:
    """Render a deterministic synthetic stereo pair with exact GT for both views.

    The scene is a slanted "road" background whose disparity grows linearly with the row (d = 8 + 24 * y / H, so
    each row is a constant sub-pixel shift, rendered with linear interpolation) and two fronto-parallel
    rectangles at integer disparities 30 and 44. Views are composed back to front, so occlusions are physical:
    a left pixel is non-occluded iff the same layer is front-most at x - d in the right view.

    Returns:
        dict with ``left``, ``right`` (H, W, 3) uint8 and ``gt``, ``gt_noc``, ``gt_right`` (H, W) float32,
        NaN = unknown (left pixels whose match falls outside the right image are in ``gt`` but not ``gt_noc``).
    """
    rng = np.random.default_rng([20240613, seed])
    pad = 64  # texture margin so shifted layers never sample outside their texture
    ys = np.arange(height, dtype=np.float32)
    xs = np.arange(width, dtype=np.float32)
    layers = []  # (texture (H, W + pad, 3), disparity (H,) per row, mask function in left coords)
    bg_disp = 8.0 + 24.0 * ys / height
    layers.append((_smooth_texture(rng, height, width + pad), bg_disp, np.ones((height, width + pad), bool)))
    for disp in (30.0, 44.0):
        h0 = int(rng.integers(height // 8, height // 2))
        w0 = int(rng.integers(width // 8, width // 2))
        box_h, box_w = int(rng.integers(height // 5, height // 3)), int(rng.integers(width // 6, width // 4))
        mask = np.zeros((height, width + pad), bool)
        mask[h0 : h0 + box_h, w0 : w0 + box_w] = True
        layers.append((_smooth_texture(rng, height, width + pad), np.full(height, disp, np.float32), mask))

    def render(sign: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # Left view (sign 0): layer pixel u sits at x = u. Right view (sign -1): at x = u - d, i.e. reads u = x + d.
        image = np.zeros((height, width, 3), np.float32)
        disp = np.full((height, width), np.nan, np.float32)
        owner = np.full((height, width), -1, np.int32)
        for index, (tex, row_disp, mask) in enumerate(layers):
            u = xs[None, :] - sign * row_disp[:, None]  # (H, W) source column in layer coordinates
            u0 = np.floor(u).astype(np.int64)
            frac = (u - u0)[..., None]
            u0c, u1c = np.clip(u0, 0, width + pad - 1), np.clip(u0 + 1, 0, width + pad - 1)
            rows = np.arange(height)[:, None]
            value = (1 - frac) * tex[rows, u0c] + frac * tex[rows, u1c]
            inside = mask[rows, u0c] & mask[rows, u1c]
            image[inside] = value[inside]
            disp[inside] = np.broadcast_to(row_disp[:, None], (height, width))[inside]
            owner[inside] = index
        return np.clip(np.round(image), 0, 255).astype(np.uint8), disp, owner

    left, gt, owner_l = render(0.0)
    right, gt_right, owner_r = render(-1.0)
    # Non-occluded: the matching right pixel x - d exists and shows the same layer.
    xr = np.round(xs[None, :] - gt).astype(np.int64)
    inside = (xr >= 0) & (xr < width)
    rows = np.broadcast_to(np.arange(height)[:, None], (height, width))
    same = np.zeros_like(inside)
    same[inside] = owner_r[rows[inside], xr[inside]] == owner_l[inside]
    gt_noc = np.where(same, gt, np.nan).astype(np.float32)
    # A right pixel whose match x + d leaves the left image has no left counterpart: unknown.
    xl = xs[None, :] + gt_right
    gt_right = np.where(xl <= width - 1, gt_right, np.nan).astype(np.float32)
    return {"left": left, "right": right, "gt": gt, "gt_noc": gt_noc, "gt_right": gt_right}


