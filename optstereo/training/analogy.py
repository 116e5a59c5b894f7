"""Transformation self-supervision for stereo ("Learning by Analogy", Liu et al., CVPR 2020), as PVStereo adopts it.

The network's prediction on the original pair, D0 (no gradient), is transformed together with the images; the
prediction on the transformed pair is supervised by the transformed D0 where D0 is reliable. This teaches the
network what PVM cannot label: pixels that the transformation makes hard (occluded by a pasted patch, cut at a new
border, blurred or noisy) while they were easy, and well predicted, in the original.

Transformations keep rows aligned, so a pair stays rectified:
- spatial: one zoom-in (sx, sy in [1, max_scale], anisotropic allowed) and one crop for both views; a disparity is a
  horizontal distance, so D_t = sx * D0 at the resampled position (the crop offset cancels between the views);
- appearance: the same colour/contrast/gamma on both views, independent noise per view, the same blur;
- occlusion: rectangles of other image content pasted into the RIGHT view only, so left pixels keep their true
  disparity while their match disappears (pasting into the left view would need the pasted object's depth).

Reliable pixels of D0 (``reliable_mask``): the match x - D0 lies inside the right image, no pixel to the right
claims the same or an earlier right column (a left-view occlusion test on D0 alone: in a rectified pair a pixel
whose match column is passed by a pixel further right is hidden in the right view), and, optionally, the
photometric error of D0 is below ``photo_threshold``.

Tensors: images (B, 3, H, W) float in [0, 255]; disparities and masks (B, 1, H, W).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from optstereo.training.analogy_config import AnalogyConfig
from optstereo.training.losses import photometric_error, sequence_huber_loss, warp_right_to_left


# -- reliability -----------------------------------------------------------------------------------------------------
def occlusion_mask(disp: torch.Tensor, tolerance: float = 1.0) -> torch.Tensor:
    """Left-view pixels hidden in the right view or matched outside it, from the left disparity alone.

    Pixel x matches right column u(x) = x - D(x). It is occluded when a pixel x' > x has u(x') < u(x) - tolerance
    (a nearer surface to its right covers its match) or when u(x) < 0.

    Args:
        disp: (B, 1, H, W) float disparity (positive).
        tolerance: px of ordering violation tolerated (sub-pixel noise of D).

    Returns:
        (B, 1, H, W) bool, True = occluded / out of frame.
    """
    w = disp.shape[-1]
    xs = torch.arange(w, device=disp.device, dtype=torch.float32)
    u = xs - disp.float()
    # min over x' > x of u(x'): a reverse cumulative minimum, shifted by one column (inf at the right border).
    rev_min = torch.flip(torch.cummin(torch.flip(u, dims=(-1,)), dim=-1).values, dims=(-1,))
    right_of = torch.cat([rev_min[..., 1:], torch.full_like(rev_min[..., :1], float("inf"))], dim=-1)
    return (right_of < u - tolerance) | (u < 0)


def reliable_mask(
    disp: torch.Tensor, left: torch.Tensor, right: torch.Tensor, cfg: AnalogyConfig
) -> torch.Tensor:
    """(B, 1, H, W) bool: pixels of D0 trusted as targets (see the module docstring)."""
    with torch.no_grad():
        mask = ~occlusion_mask(disp, cfg.occ_tolerance)
        if cfg.photo_threshold > 0:
            warped, inside = warp_right_to_left(right.float() / 255.0, disp)
            err = photometric_error(left.float() / 255.0, warped, color_norm="mean")  # photo_threshold's scale
            mask = mask & inside & (err < cfg.photo_threshold)
    return mask


# -- the transformations -------------------------------------------------------------------------------------------
@dataclass
class SpatialParams:
    """Per-sample zoom (sx, sy >= 1) and crop offset (x0, y0) in zoomed pixels; each a (B,) float32 tensor."""

    sx: torch.Tensor
    sy: torch.Tensor
    x0: torch.Tensor
    y0: torch.Tensor


def sample_spatial(batch: int, height: int, width: int, max_scale: float, gen: torch.Generator) -> SpatialParams:
    """Random zoom factors in [1, max_scale] and crop offsets that keep the (H, W) window inside the zoomed image."""
    sx = 1.0 + (max_scale - 1.0) * torch.rand(batch, generator=gen)
    sy = 1.0 + (max_scale - 1.0) * torch.rand(batch, generator=gen)
    x0 = torch.rand(batch, generator=gen) * (width * sx - width)
    y0 = torch.rand(batch, generator=gen) * (height * sy - height)
    return SpatialParams(sx, sy, x0, y0)


def _spatial_grid(params: SpatialParams, height: int, width: int, device: torch.device) -> torch.Tensor:
    """grid_sample grid (B, H, W, 2), align_corners=False: output pixel centre u + 0.5 samples (u + 0.5 + x0) / sx."""
    sx, sy, x0, y0 = (t.to(device).view(-1, 1, 1) for t in (params.sx, params.sy, params.x0, params.y0))
    u = torch.arange(width, device=device, dtype=torch.float32).view(1, 1, width) + 0.5
    v = torch.arange(height, device=device, dtype=torch.float32).view(1, height, 1) + 0.5
    gx = 2.0 * ((u + x0) / sx) / width - 1.0
    gy = 2.0 * ((v + y0) / sy) / height - 1.0
    return torch.stack(torch.broadcast_tensors(gx, gy), dim=-1)


def apply_spatial(
    params: SpatialParams, images: list[torch.Tensor], disp: torch.Tensor, mask: torch.Tensor
) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor]:
    """Zoom + crop images (bilinear), disparity and mask (nearest: no mixing across depth edges); D scaled by sx.

    Returns:
        (images, disp (B, 1, H, W) float32, mask (B, 1, H, W) bool), all of the input size.
    """
    b, _, h, w = disp.shape
    grid = _spatial_grid(params, h, w, disp.device)
    out_images = [F.grid_sample(img.float(), grid, mode="bilinear", padding_mode="border", align_corners=False)
                  for img in images]
    scale = params.sx.to(disp.device).view(-1, 1, 1, 1)
    out_disp = F.grid_sample(disp.float(), grid, mode="nearest", padding_mode="border", align_corners=False) * scale
    out_mask = F.grid_sample(mask.float(), grid, mode="nearest", padding_mode="zeros", align_corners=False) > 0.5
    return out_images, out_disp, out_mask


def paste_occluders(
    right: torch.Tensor, source: torch.Tensor, cfg: AnalogyConfig, gen: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """Paste 1..max_patches rectangles cut from ``source`` (another image per sample) into ``right``.

    Args:
        right, source: (B, 3, H, W) float.

    Returns:
        (new right (B, 3, H, W), pasted (B, 1, H, W) bool, True where a rectangle covers the pixel and the value
        changed).
    """
    b, _, h, w = right.shape
    pasted = torch.zeros(b, 1, h, w, dtype=torch.bool)
    shifts = []
    lo, hi = cfg.patch_frac
    for i in range(b):
        n = int(torch.randint(1, cfg.max_patches + 1, (1,), generator=gen))
        for _ in range(n):
            ph = max(1, int(h * (lo + (hi - lo) * float(torch.rand(1, generator=gen)))))
            pw = max(1, int(w * (lo + (hi - lo) * float(torch.rand(1, generator=gen)))))
            y = int(torch.randint(0, h - ph + 1, (1,), generator=gen))
            x = int(torch.randint(0, w - pw + 1, (1,), generator=gen))
            pasted[i, 0, y : y + ph, x : x + pw] = True
        # cut the content from a random place of the source so the patch does not repeat the right view's own pixels
        shifts.append((int(torch.randint(0, h, (1,), generator=gen)), int(torch.randint(0, w, (1,), generator=gen))))
    pasted = pasted.to(right.device)
    content = torch.stack([torch.roll(source[i], shifts=s, dims=(-2, -1)) for i, s in enumerate(shifts)])
    new_right = torch.where(pasted, content.to(right.dtype), right)
    return new_right, pasted & (new_right != right).any(dim=1, keepdim=True)


def occlude_right(
    left: torch.Tensor, right: torch.Tensor, p: float, cfg: AnalogyConfig, gen: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """Occluders pasted into the RIGHT view of each sample with probability ``p`` (training input only).

    The L_T occluders (``paste_occluders``: 1..max_patches rectangles of patch_frac size, cut from another sample's
    left view) without a second forward pass: the left label of an occluded pixel is still its true disparity, so the
    PVM label supervises it (L_P), while the photometric terms keep seeing the clean pair.

    Args:
        left, right: (B, 3, H, W) float [0, 255].
        p: probability per sample in [0, 1].

    Returns:
        (right (B, 3, H, W), pasted (B, 1, H, W) bool: True where a chosen sample's pixel changed).
    """
    with torch.no_grad():
        source = torch.roll(left, shifts=1, dims=0) if left.shape[0] > 1 else torch.flip(left, dims=(-1,))
        pasted_right, pasted = paste_occluders(right, source, cfg, gen)
        chosen = (torch.rand(right.shape[0], generator=gen) < p).view(-1, 1, 1, 1).to(right.device)
        return torch.where(chosen, pasted_right, right), pasted & chosen


def _gaussian_blur(images: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian blur with a per-sample sigma (B,), 5-tap kernel; sigma 0 leaves the image unchanged."""
    taps = torch.arange(-2, 3, device=images.device, dtype=torch.float32)
    sigma = sigma.to(images.device).clamp(min=1e-3).view(-1, 1)
    kernel = torch.exp(-0.5 * (taps / sigma) ** 2)
    kernel = kernel / kernel.sum(dim=1, keepdim=True)  # (B, 5)
    b, c, h, w = images.shape
    x = images.reshape(1, b * c, h, w)
    kx = kernel.repeat_interleave(c, dim=0).view(b * c, 1, 1, 5)
    x = F.conv2d(F.pad(x, (2, 2, 0, 0), mode="replicate"), kx, groups=b * c)
    x = F.conv2d(F.pad(x, (0, 0, 2, 2), mode="replicate"), kx.view(b * c, 1, 5, 1), groups=b * c)
    return x.view(b, c, h, w)


def apply_appearance(
    left: torch.Tensor, right: torch.Tensor, cfg: AnalogyConfig, gen: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """Shared brightness/contrast/gamma, per-view noise, shared blur; returns images clamped to [0, 255]."""
    b = left.shape[0]
    dev = left.device

    def draw(lo: float, hi: float) -> torch.Tensor:
        return (lo + (hi - lo) * torch.rand(b, generator=gen)).to(dev).view(b, 1, 1, 1)

    brightness, contrast, gamma = draw(0.7, 1.3), draw(0.7, 1.3), draw(0.8, 1.25)
    sigma_blur = (cfg.max_blur * torch.rand(b, generator=gen)) * (torch.rand(b, generator=gen) < 0.5)
    sigma_noise = draw(0.0, cfg.noise_std)
    out = []
    for img in (left, right):
        x = img.float() / 255.0 * brightness
        mean = x.mean(dim=(1, 2, 3), keepdim=True)
        x = ((x - mean) * contrast + mean).clamp(0.0, 1.0) ** gamma * 255.0
        if cfg.max_blur > 0:
            x = _gaussian_blur(x, sigma_blur)
        noise = torch.randn(x.shape, generator=gen).to(dev)
        out.append((x + noise * sigma_noise).clamp(0.0, 255.0))
    return out[0], out[1]


@dataclass
class AnalogySample:
    """A transformed batch and its target: left/right (B, 3, H, W), target (B, 1, H, W), valid (B, 1, H, W) bool."""

    left: torch.Tensor
    right: torch.Tensor
    target: torch.Tensor
    valid: torch.Tensor


def transform_batch(
    left: torch.Tensor,
    right: torch.Tensor,
    disp: torch.Tensor,
    cfg: AnalogyConfig,
    gen: torch.Generator,
) -> AnalogySample:
    """Build the transformed pair and its target from the original pair and D0 (detached here).

    Args:
        left, right: (B, 3, H, W) float [0, 255] original pair.
        disp: (B, 1, H, W) D0, the network's prediction on it (gradients are cut).
        cfg: which transformations run, and their ranges.
        gen: CPU torch.Generator (reproducible per step).
    """
    with torch.no_grad():
        disp = disp.detach().float()
        valid = reliable_mask(disp, left, right, cfg)
        images = [left.float(), right.float()]
        target = disp
        if cfg.spatial:
            b, _, h, w = disp.shape
            params = sample_spatial(b, h, w, cfg.max_scale, gen)
            images, target, valid = apply_spatial(params, images, disp, valid)
        t_left, t_right = images
        if cfg.occlusion:
            source = torch.roll(t_left, shifts=1, dims=0) if t_left.shape[0] > 1 else torch.flip(t_left, dims=(-1,))
            t_right, _ = paste_occluders(t_right, source, cfg, gen)
        if cfg.appearance:
            t_left, t_right = apply_appearance(t_left, t_right, cfg, gen)
    return AnalogySample(t_left, t_right, target, valid)


def analogy_loss(
    preds: list[torch.Tensor], sample: AnalogySample, gamma: float = 0.8
) -> torch.Tensor:
    """L_T: the sequence Huber loss of the transformed pair's predictions against the transformed D0 (reliable px)."""
    return sequence_huber_loss(preds, sample.target, sample.valid, gamma)
