"""The PVStereo loss (paper Section III-C): L = L_P + lambda_1 L_R + lambda_2 L_S.

Functional forms (``huber``, ``sequence_weights``, ``sequence_huber_loss``, ``warp_right_to_left``,
``ssim``, ``reconstruction_loss``, ``smoothness_loss``) and a thin ``PVStereoLoss`` module.
Images are (B, 3, H, W) float in [0, 255] (as fed to the network) and are divided by 255 here;
disparities are (B, 1, H, W), positive (left(x) matches right(x - d)), full resolution.
Every term is computed in float32 (autocast off) whatever the prediction dtype.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from optstereo.choices import SMOOTHNESS_NORMS, SMOOTHNESS_ORDERS
from optstereo.training.sections import LossConfig

# the LossConfig fields this module reads; the others (conf_weight, lambda_t, analogy*) are the trainer's
TERM_FIELDS = (
    "gamma", "lambda_r", "lambda_s", "alpha", "photometric_iters", "smoothness_norm", "smoothness_order", "color_norm",
)
SSIM_C1 = 0.01**2  # SSIM stabilisers for images in [0, 1] (Wang et al. 2004; Monodepth)
SSIM_C2 = 0.03**2


def huber(x: torch.Tensor) -> torch.Tensor:
    """The paper's Huber function on x >= 0: x - 0.5 if x >= 1 else x^2 / 2 (elementwise)."""
    return torch.where(x >= 1.0, x - 0.5, 0.5 * x * x)


def sequence_weights(n: int, gamma: float = 0.8, device: torch.device | None = None) -> torch.Tensor:
    """Weights gamma^(N - i) for i = 1..N, normalised to sum 1 (the last iteration weighs most)."""
    exps = torch.arange(n - 1, -1, -1, device=device, dtype=torch.float32)
    w = torch.pow(torch.tensor(gamma, dtype=torch.float32, device=device), exps)
    return w / w.sum()


def _check_pred_list(preds: Sequence[torch.Tensor] | torch.Tensor) -> list[torch.Tensor]:
    if isinstance(preds, torch.Tensor):
        preds = [preds]
    if len(preds) == 0:
        raise ValueError("preds is empty: expected a list of N_s disparities (B, 1, H, W)")
    return list(preds)


def sequence_huber_loss(
    preds: Sequence[torch.Tensor] | torch.Tensor,
    label: torch.Tensor,
    valid: torch.Tensor | None = None,
    gamma: float = 0.8,
    weight: torch.Tensor | None = None,
) -> torch.Tensor:
    """L_P, the PVM guiding loss (paper eq. (guiding loss)); also the supervised loss on ground truth.

    L_P = sum_i gamma^(N - i) * mean_{p labelled} l(|D~(p) - D^i(p)|) / sum_i gamma^(N - i).

    Args:
        preds: N full-resolution predictions D^1..D^N, each (B, 1, H, W).
        label: (B, 1, H, W) float label D~ (NaN = no label).
        valid: (B, 1, H, W) bool, optional; pixels used are valid & isfinite(label). The mean is over all
            used pixels of the batch (a sample with more labels weighs more, like RAFT's sequence loss).
        weight: (B, 1, H, W) float >= 0, optional per-pixel weights (PVM confidence): the mean becomes
            sum(w * l) / sum(w) over the used pixels.

    Returns:
        Scalar float32 tensor; 0 (still connected to the graph) if no pixel is labelled.
    """
    preds = _check_pred_list(preds)
    if label.shape != preds[0].shape:
        raise ValueError(f"label shape {tuple(label.shape)} differs from prediction shape {tuple(preds[0].shape)}")
    if valid is not None and valid.shape != label.shape:
        raise ValueError(f"valid shape {tuple(valid.shape)} differs from label shape {tuple(label.shape)}")
    with torch.autocast(device_type=label.device.type, enabled=False):
        mask = torch.isfinite(label) if valid is None else valid.bool() & torch.isfinite(label)
        target = torch.where(mask, label.float(), torch.zeros((), device=label.device))
        weights = sequence_weights(len(preds), gamma, device=label.device)
        zero = torch.zeros((), device=label.device)
        pixel_w = mask.float() if weight is None else torch.where(mask, weight.float(), zero)
        count = mask.sum().clamp(min=1) if weight is None else pixel_w.sum().clamp(min=1e-6)
        total = preds[0].float().sum() * 0.0  # keeps the graph when nothing is labelled
        for w, pred in zip(weights, preds, strict=True):
            err = huber((pred.float() - target).abs())
            total = total + w * (torch.where(mask, err, zero) * pixel_w).sum() / count
    return total


def warp_right_to_left(right: torch.Tensor, disp: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Differentiable bilinear warp of the right view to the left: I^_l(x, y) = I_r(x - D(x, y), y).

    Args:
        right: (B, C, H, W) float image.
        disp: (B, 1, H, W) float disparity (positive).

    Returns:
        warped (B, C, H, W) float32, valid (B, 1, H, W) bool where x - D lies in [0, W - 1] (NaN D -> False).
    """
    b, _, h, w = right.shape
    if disp.shape != (b, 1, h, w):
        raise ValueError(f"disp must be (B, 1, H, W) = {(b, 1, h, w)}, got {tuple(disp.shape)}")
    with torch.autocast(device_type=right.device.type, enabled=False):
        xs = torch.arange(w, device=right.device, dtype=torch.float32).view(1, 1, 1, w)
        ys = torch.arange(h, device=right.device, dtype=torch.float32).view(1, 1, h, 1)
        x_src = xs - disp.float()  # (B, 1, H, W)
        valid = (x_src >= 0) & (x_src <= w - 1)
        # align_corners=True: -1 and +1 are the centres of the first and last pixel.
        gx = 2.0 * x_src / max(w - 1, 1) - 1.0
        gy = (2.0 * ys / max(h - 1, 1) - 1.0).expand_as(gx)
        grid = torch.stack([gx[:, 0], gy[:, 0]], dim=-1)  # (B, H, W, 2)
        grid = torch.nan_to_num(grid, nan=-2.0)  # NaN disparity samples zeros and is invalid anyway
        warped = F.grid_sample(right.float(), grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    return warped, valid


def ssim(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM with a 3x3 average-pool window (Monodepth), reflection padding keeps the size.

    Args:
        x, y: (B, C, H, W) float images in [0, 1].

    Returns:
        (B, C, H, W) SSIM map (1 where x == y).
    """
    x = F.pad(x, (1, 1, 1, 1), mode="reflect")
    y = F.pad(y, (1, 1, 1, 1), mode="reflect")
    mu_x = F.avg_pool2d(x, 3, 1)
    mu_y = F.avg_pool2d(y, 3, 1)
    sigma_x = F.avg_pool2d(x * x, 3, 1) - mu_x * mu_x
    sigma_y = F.avg_pool2d(y * y, 3, 1) - mu_y * mu_y
    sigma_xy = F.avg_pool2d(x * y, 3, 1) - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * sigma_xy + SSIM_C2)
    den = (mu_x * mu_x + mu_y * mu_y + SSIM_C1) * (sigma_x + sigma_y + SSIM_C2)
    return num / den


def _combine_channels(x: torch.Tensor, color_norm: str) -> torch.Tensor:
    """(B, C, H, W) non-negative -> (B, 1, H, W): the L1 norm over channels ("l1") or their mean ("mean")."""
    if color_norm == "l1":
        return x.sum(dim=1, keepdim=True)
    if color_norm == "mean":
        return x.mean(dim=1, keepdim=True)
    raise ValueError(f"color_norm must be 'l1' or 'mean', got {color_norm!r}")


def photometric_error(left: torch.Tensor, warped: torch.Tensor, alpha: float = 0.85,
                      color_norm: str = "l1") -> torch.Tensor:
    """alpha (1 - SSIM) / 2 + (1 - alpha) ||I_l - I^_l||: (B, 3, H, W) [0, 1] -> (B, 1, H, W).

    SSIM is averaged over channels; the photometric difference is the L1 norm over channels (the paper's
    equation) or, with ``color_norm="mean"``, its channel mean.
    """
    dssim = ((1.0 - ssim(left, warped)) / 2.0).clamp(0.0, 1.0).mean(dim=1, keepdim=True)
    l1 = _combine_channels((left - warped).abs(), color_norm)
    return alpha * dssim + (1.0 - alpha) * l1


def reconstruction_loss(
    left: torch.Tensor, right: torch.Tensor, disp: torch.Tensor, alpha: float = 0.85, color_norm: str = "l1"
) -> torch.Tensor:
    """L_R: photometric error between I_l and I_r warped by D, averaged over pixels warping inside I_r.

    Args:
        left, right: (B, 3, H, W) float in [0, 255].
        disp: (B, 1, H, W) float full-resolution disparity.
        alpha: SSIM weight (paper: 0.85).
        color_norm: "l1" (the paper) or "mean", see :func:`photometric_error`.

    Returns:
        Scalar float32 tensor (0, still connected to the graph, if no pixel warps inside).
    """
    if left.shape != right.shape:
        raise ValueError(f"left/right shapes differ: {tuple(left.shape)} vs {tuple(right.shape)}")
    with torch.autocast(device_type=left.device.type, enabled=False):
        warped, valid = warp_right_to_left(right.float() / 255.0, disp)
        err = photometric_error(left.float() / 255.0, warped, alpha, color_norm)
        count = valid.sum().clamp(min=1)
        return torch.where(valid, err, torch.zeros((), device=err.device)).sum() / count


def smoothness_loss(disp: torch.Tensor, image: torch.Tensor, normalize: str = "none",
                    color_norm: str = "l1", order: int = 1) -> torch.Tensor:
    """L_S, edge-aware smoothness of ``order`` 1 (the paper) or 2 (a planar prior).

    order 1: mean |dx D| exp(-||dx I_l||) + mean |dy D| exp(-||dy I_l||).
    order 2: mean |dxx D| exp(-max(||dx I_l||) of the two differences dxx spans) + the same along y;
        dxx D(x) = D(x+1) - 2 D(x) + D(x-1), zero on any plane, so slanted surfaces cost nothing.

    Args:
        disp: (B, 1, H, W) float disparity.
        image: (B, 3, H, W) float in [0, 255]; gradients are taken on image / 255.
        normalize: "none" = the paper's eq. on D itself; "mean" = D / mean(D) per image (Monodepth2).
        color_norm: ||dI|| = the L1 norm over channels ("l1", the paper) or their mean ("mean").
        order: 1 or 2, the order of the disparity differences.

    Returns:
        Scalar float32 tensor.
    """
    if normalize not in SMOOTHNESS_NORMS:
        raise ValueError(f"normalize must be one of {SMOOTHNESS_NORMS}, got {normalize!r}")
    if order not in SMOOTHNESS_ORDERS:
        raise ValueError(f"order must be one of {SMOOTHNESS_ORDERS}, got {order!r}")
    if disp.ndim != 4 or disp.shape[1] != 1 or image.ndim != 4 or disp.shape[-2:] != image.shape[-2:]:
        raise ValueError(f"smoothness_loss needs disp (B, 1, H, W) and image (B, 3, H, W) of one size, got "
                         f"{tuple(disp.shape)} and {tuple(image.shape)}")
    with torch.autocast(device_type=disp.device.type, enabled=False):
        d = disp.float()
        if normalize == "mean":
            d = d / (d.mean(dim=(2, 3), keepdim=True).abs() + 1e-7)
        img = image.float() / 255.0
        total = torch.zeros((), device=d.device)
        for dim in (-1, -2):  # x, then y
            d_d = torch.diff(d, dim=dim)
            edge = _combine_channels(torch.diff(img, dim=dim).abs(), color_norm)
            if order == 2:
                # a second difference straddles two first differences; either one being an edge excuses it
                d_d = torch.diff(d_d, dim=dim)
                n = edge.shape[dim] - 1
                edge = torch.maximum(edge.narrow(dim, 0, n), edge.narrow(dim, 1, n))
            if d_d.numel():  # an image too small for this order along this axis adds nothing (not NaN)
                total = total + (d_d.abs() * torch.exp(-edge)).mean()
        return total


class PVStereoLoss(nn.Module):
    """L = L_P + lambda_r L_R + lambda_s L_S over a list of predictions.

    L_P covers every iteration with the gamma weights. L_R and L_S apply to the final prediction only by
    default (``photometric_iters="last"``); "all" applies them to every iteration with the same normalised
    gamma weights (8x the full-resolution warps). A term whose lambda is 0 is not computed (reported as 0),
    which is the supervised mode (L_P on ground truth).

    forward(preds, left, right, label, valid, weight=None) -> (total, terms):
        preds: list of (B, 1, H, W); left, right: (B, 3, H, W) in [0, 255]; label (B, 1, H, W) float (NaN = none);
        valid (B, 1, H, W) bool or None; weight (B, 1, H, W) per-pixel L_P weights (confidence) or None.
        total is the differentiable scalar; terms holds detached float32 scalars "L_P", "L_R", "L_S", "total".
    """

    def __init__(
        self,
        gamma: float = 0.8,
        lambda_r: float = 0.1,
        lambda_s: float = 0.1,
        alpha: float = 0.85,
        photometric_iters: str = "last",
        smoothness_norm: str = "none",
        color_norm: str = "l1",
        smoothness_order: int = 1,
    ) -> None:
        super().__init__()
        if lambda_r is None or lambda_s is None:
            raise ValueError("lambda_r and lambda_s must be numbers (None, by supervision, is for TrainConfig)")
        self.config = LossConfig(
            gamma=gamma,
            lambda_r=lambda_r,
            lambda_s=lambda_s,
            alpha=alpha,
            photometric_iters=photometric_iters,
            smoothness_norm=smoothness_norm,
            smoothness_order=smoothness_order,
            color_norm=color_norm,
        )

    @classmethod
    def from_config(cls, cfg: LossConfig) -> PVStereoLoss:
        """The module of ``cfg``'s L_P/L_R/L_S knobs (conf_weight and L_T are applied by the trainer)."""
        return cls(**{k: getattr(cfg, k) for k in TERM_FIELDS})

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={getattr(self.config, k)}" for k in TERM_FIELDS)

    def forward(
        self,
        preds: Sequence[torch.Tensor] | torch.Tensor,
        left: torch.Tensor,
        right: torch.Tensor,
        label: torch.Tensor,
        valid: torch.Tensor | None = None,
        weight: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        cfg = self.config
        preds = _check_pred_list(preds)
        loss_p = sequence_huber_loss(preds, label, valid, cfg.gamma, weight)
        if cfg.photometric_iters == "last":
            photo_preds, photo_weights = preds[-1:], torch.ones(1, device=label.device)
        else:
            photo_preds, photo_weights = preds, sequence_weights(len(preds), cfg.gamma, device=label.device)
        loss_r = torch.zeros((), device=label.device)
        loss_s = torch.zeros((), device=label.device)
        for w, pred in zip(photo_weights, photo_preds, strict=True):
            if cfg.lambda_r > 0:
                loss_r = loss_r + w * reconstruction_loss(left, right, pred, cfg.alpha, cfg.color_norm)
            if cfg.lambda_s > 0:
                loss_s = loss_s + w * smoothness_loss(pred, left, cfg.smoothness_norm, cfg.color_norm,
                                                       cfg.smoothness_order)
        total = loss_p + cfg.lambda_r * loss_r + cfg.lambda_s * loss_s
        terms = {
            "L_P": loss_p.detach(),
            "L_R": loss_r.detach(),
            "L_S": loss_s.detach(),
            "total": total.detach(),
        }
        return total, terms
