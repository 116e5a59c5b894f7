"""Joint training augmentations on numpy samples: flip-swap, spatial scale, random crop, photometric jitter, to
tensors.

All functions take an explicit ``numpy.random.Generator`` so a sample's augmentation is a pure function of its
seed; the stream derives that seed from (seed, epoch, global worker id, sample counter), which makes training
reproducible and resumable.

Arrays: images (H, W, 3) uint8 RGB; labels (H, W) float32 with NaN = no label (positive disparities).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import torch

from optstereo.inference.rescale import rescaled_pair, sparse_to_size
from optstereo.training.augment import flip_swap
from optstereo.training.sections import parse_scale_range

logger = logging.getLogger(__name__)

Image = npt.NDArray[np.uint8]
Disp = npt.NDArray[np.float32]


def crop_window(height: int, width: int, crop: tuple[int, int], rng: np.random.Generator) -> tuple[int, int, int, int]:
    """Random (y0, x0, h, w) window of size ``crop``; a frame smaller than the crop uses the whole frame.

    The window sides are rounded down to multiples of 8 (the network works at 1/8 resolution), so a 375x1242
    KITTI frame with a 512x1024 crop gives a 368x1024 window.
    """
    h = min(crop[0], height) // 8 * 8
    w = min(crop[1], width) // 8 * 8
    if h < 8 or w < 8:
        raise ValueError(f"frame {height}x{width} is smaller than the network's minimum 8x8 input")
    y0 = int(rng.integers(0, height - h + 1))
    x0 = int(rng.integers(0, width - w + 1))
    return y0, x0, h, w


def random_crop(arrays: list[np.ndarray | None], crop: tuple[int, int], rng: np.random.Generator) -> list:
    """Crop every (H, W, ...) array of one sample with the same random window (None entries pass through)."""
    first = next(a for a in arrays if a is not None)
    y0, x0, h, w = crop_window(first.shape[0], first.shape[1], crop, rng)
    return [None if a is None else np.ascontiguousarray(a[y0 : y0 + h, x0 : x0 + w]) for a in arrays]


def photometric_jitter(left: Image, right: Image, rng: np.random.Generator) -> tuple[Image, Image]:
    """Colour jitter shared by both views plus a small per-view brightness change.

    Shared: brightness x[0.8, 1.2], contrast x[0.8, 1.2], saturation x[0.8, 1.2], gamma [0.9, 1.1]. Per view:
    brightness x[0.95, 1.05], which imitates the exposure differences of real rigs without breaking matching
    (RAFT-Stereo's asymmetric jitter serves the same purpose).
    """
    brightness, contrast, saturation = rng.uniform(0.8, 1.2, size=3)
    gamma = rng.uniform(0.9, 1.1)
    out = []
    for img in (left, right):
        x = img.astype(np.float32) / 255.0
        x = x * brightness * rng.uniform(0.95, 1.05)
        mean = x.mean()
        x = (x - mean) * contrast + mean
        grey = x.mean(axis=2, keepdims=True)
        x = (x - grey) * saturation + grey
        x = np.clip(x, 0.0, 1.0) ** gamma
        out.append((x * 255.0 + 0.5).astype(np.uint8))
    return out[0], out[1]


def rescale_sample(left: Image, right: Image, label: Disp, weight: Disp | None,
                   scale: float) -> tuple[Image, Image, Disp, Disp | None]:
    """One training sample resized by ``scale`` (optstereo.inference.rescale): the pair smoothly, the sparse label and
    its
    confidence by nearest neighbour, the label's disparities times the width ratio."""
    left, right = rescaled_pair(left, right, scale)
    shape = left.shape[:2]
    label = sparse_to_size(label, shape)
    return left, right, label, None if weight is None else sparse_to_size(weight, shape, scale_values=False)


@dataclass(frozen=True)
class TrainTransform:
    """flip-swap (p) -> spatial scale (off by default) -> random crop -> optional photometric jitter, on one sample.

    Attributes:
        crop: (H, W) crop size (whole frame when smaller, rounded down to multiples of 8).
        flip_swap_p: probability of flip-swap; samples without a right-view label are never flipped.
        photometric: apply photometric_jitter.
        scale_range: (lo, hi): before the crop, the whole sample is resized by s ~ U(lo, hi) (images area/bilinear,
            labels and confidences nearest, disparities times the width ratio); (1, 1) = off and draws nothing, so
            runs without it keep their random sequence.
    """

    crop: tuple[int, int] = (320, 736)
    flip_swap_p: float = 0.5
    photometric: bool = False
    scale_range: tuple[float, float] = (1.0, 1.0)

    def __post_init__(self) -> None:
        # The config's own parser: a list [1, 1] from YAML is "off" too, and a bad range fails the same way.
        object.__setattr__(self, "scale_range", parse_scale_range(self.scale_range))
        if not 0 <= self.flip_swap_p <= 1:  # 2.0 was taken as "always"
            raise ValueError(f"flip_swap_p is a probability in [0, 1], got {self.flip_swap_p}")

    def __call__(
        self, left: Image, right: Image, label: Disp, label_right: Disp | None, rng: np.random.Generator,
        weight: Disp | None = None, weight_right: Disp | None = None,
    ) -> tuple[Image, Image, Disp] | tuple[Image, Image, Disp, Disp]:
        """Returns augmented (left, right, label); shapes (h, w, 3), (h, w, 3), (h, w).

        With ``weight`` (the left view's per-pixel PVM confidence) it returns (left, right, label, weight), the weight
        cropped like the label. A flip-swapped sample takes ``weight_right`` (the right view's, mirrored with it),
        or weight 1 everywhere when the shards hold no right-view confidence. The random draws are the same with or
        without weights.
        """
        # Draw the flip decision even when it cannot be applied so the random sequence does not depend on data.
        do_flip = rng.random() < self.flip_swap_p
        if do_flip and label_right is not None:
            left, right, label, label_right = flip_swap(left, right, label, label_right)
            if weight is not None:
                weight = (np.ones(label.shape, dtype=np.float32) if weight_right is None
                          else np.ascontiguousarray(weight_right[:, ::-1], dtype=np.float32))
        if self.scale_range != (1.0, 1.0):
            left, right, label, weight = rescale_sample(left, right, label, weight, rng.uniform(*self.scale_range))
        left, right, label, weight = random_crop([left, right, label, weight], self.crop, rng)
        if self.photometric:
            left, right = photometric_jitter(left, right, rng)
        return (left, right, label) if weight is None else (left, right, label, weight)


def to_tensors(
    left: Image, right: Image, label: Disp, max_disp: float = float("inf")
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """numpy sample -> (left, right (3, H, W) float32 [0, 255], label (1, H, W) float32, valid (1, H, W) bool).

    Valid pixels have a finite label in [0, max_disp); the label is 0 elsewhere so no NaN reaches the loss.
    """
    label = np.asarray(label, dtype=np.float32)
    valid = np.isfinite(label) & (label >= 0) & (label < max_disp)
    label = np.where(valid, label, 0.0).astype(np.float32)
    to_chw = lambda img: torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1))).float()  # noqa: E731
    return to_chw(left), to_chw(right), torch.from_numpy(label)[None], torch.from_numpy(valid)[None]


def collate_min_size(batch: list[tuple]) -> tuple:
    """Default-collate a batch after cropping every item to the batch's smallest (H, W) (top-left).

    Items are already random crops, so trimming keeps them random; it only matters when frames smaller than the
    crop meet (different datasets / the `sample` dataset's pairs of different sizes).
    """
    h = min(item[0].shape[-2] for item in batch)
    w = min(item[0].shape[-1] for item in batch)
    trimmed = [tuple(x[..., :h, :w] if isinstance(x, torch.Tensor) else x for x in item) for item in batch]
    return torch.utils.data.default_collate(trimmed)
