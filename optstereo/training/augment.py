"""Flip-swap augmentation of PVStereo (paper Section III-C) for NumPy arrays and torch tensors.

(I_l, I_r, D~_l, D~_r) -> (flip(I_r), flip(I_l), flip(D~_r), flip(D~_l)), flip = horizontal mirror.
Mirroring a rectified pair makes the old right view a valid LEFT view: right(x) matched left(x + d),
so after mirroring, new_left(x') = flip(right) matches new_right(x' - d), a positive disparity. Its
label is therefore the flipped RIGHT-view label; RAFT-Stereo's flip mode keeps the left label, which
is wrong (that label belongs to the other view).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import numpy as np
import torch

ArrayT = TypeVar("ArrayT", np.ndarray, torch.Tensor)


def _flip(x: ArrayT | None) -> ArrayT | None:
    if x is None:
        return None
    if isinstance(x, torch.Tensor):
        if x.ndim >= 3 and x.shape[-1] in (3, 4) and x.shape[-3] not in (1, 3, 4):  # flipping colours, not columns
            raise ValueError(f"torch inputs must be (..., H, W) (channels first), got shape {tuple(x.shape)}: an "
                             "(H, W, C) image? x.permute(2, 0, 1)")
        return torch.flip(x, dims=(-1,))  # (..., H, W)
    if isinstance(x, np.ndarray):
        if x.ndim not in (2, 3) or (x.ndim == 3 and x.shape[2] not in (1, 3, 4)):  # (C, H, W) flipped rows
            raise ValueError(f"numpy inputs must be (H, W) or (H, W, C), got shape {x.shape}")
        return np.ascontiguousarray(x[:, ::-1])  # W is axis 1 for both (H, W) and (H, W, C)
    raise TypeError(f"flip_swap expects numpy arrays or torch tensors, got {type(x).__name__}")


def flip_swap(
    left: ArrayT, right: ArrayT, label_left: ArrayT | None, label_right: ArrayT | None
) -> tuple[ArrayT, ArrayT, ArrayT | None, ArrayT | None]:
    """Mirror a stereo sample horizontally and swap the views (and their labels).

    Args:
        left, right: images, numpy (H, W, C) or torch (..., H, W) (e.g. (3, H, W)).
        label_left, label_right: disparities of each view (positive, NaN = no label), numpy (H, W) or
            torch (..., H, W); None passes through (the new left label is None if label_right is None).

    Returns:
        (new_left, new_right, new_label_left, new_label_right) =
        (flip(right), flip(left), flip(label_right), flip(label_left)); NumPy outputs are contiguous copies.
        Applying it twice gives back the inputs.
    """
    for x in (left, right):
        if not isinstance(x, (np.ndarray, torch.Tensor)):
            raise TypeError(f"flip_swap expects numpy arrays or torch tensors, got {type(x).__name__}")
    if tuple(left.shape) != tuple(right.shape):
        raise ValueError(f"left/right shapes differ: {tuple(left.shape)} vs {tuple(right.shape)}")
    return _flip(right), _flip(left), _flip(label_right), _flip(label_left)


def right_view(predict: Callable[[np.ndarray, np.ndarray], np.ndarray], left: np.ndarray,
               right: np.ndarray) -> np.ndarray:
    """The RIGHT view's (H, W) disparity (right(x) matches left(x + d)) of an (H, W, 3) pair: ``predict`` (any
    left-view matcher, (left, right) -> (H, W)) on the flip-swapped pair, mirrored back."""
    mirrored_left, mirrored_right, _, _ = flip_swap(left, right, None, None)
    return _flip(predict(mirrored_left, mirrored_right))
