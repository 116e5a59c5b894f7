"""HITNet (Tankovich et al., CVPR 2021), compact, for PVM-HITNet: PVM labels train a second supervised network.

Paper part -> module (tile hypotheses and their geometry: tiles.py):
    multi-resolution feature extractor e_0..e_{L-1}  UNetFeatures: U-Net, levels at 1/2, 1/4, ..., 1/2^L
    tile features, local cost volume, argmin, p       TileInit (per level): 4x4 conv (stride 4 left, (4, 1) right)
    propagation: warp by the plane, costs, CNN U,     PropagationStep (per level, plus one shared for the extra
        update of (d, dx, dy, p), confidence w            finest-level steps): softmax(w) blends two hypotheses
    slanted-plane upsampling to full resolution       tiles.planes_to_pixels

Level l has features at stride s_l = 2^(l+1) and tiles of TILE x TILE features, i.e. TILE * s_l full-resolution
pixels (8, 16, 32, 64 for four levels). Coarse levels round their sizes up, so any H, W divisible by 8 (the finest
tile) works. What is simplified against the paper, and why, is in docs/optstereo.md ("PVM-HITNet").

Reference: Tankovich, Häne, Zhang, Kowdle, Fanello, Bouaziz, "HITNet: Hierarchical Iterative Tile Refinement
Network for Real-time Stereo Matching", CVPR 2021.
"""

from __future__ import annotations

from typing import ClassVar

import torch
import torch.nn.functional as F
from torch import nn

from optstereo.models.hitnet_config import HITNetConfig
from optstereo.models.optstereo import check_stereo_pair, normalize_image, resolve_iters
from optstereo.models.tiles import (
    DESC_DIM,
    HYP_DIM,
    TILE,
    cost_volume,
    pad_to_tiles,
    planes_to_pixels,
    soft_argmin,
    tile_costs,
    tiles_to_pixels,
    upsample_hypotheses,
)

LEAK = 0.2  # HITNet uses leaky ReLUs throughout and no normalisation
FINEST_STRIDE = 2  # stride of the finest feature level; its tiles are TILE * 2 = 8 full-resolution pixels
UPDATE_INIT_SCALE = 0.1  # shrinks the last conv's initial weights: the first updates stay small next to the init


def conv_act(in_channels: int, out_channels: int, *, kernel: int = 3, stride: int = 1, dilation: int = 1) -> nn.Module:
    """Conv ('same' padding for stride 1) + leaky ReLU: (B, in, H, W) -> (B, out, ceil(H / stride), ...)."""
    pad = dilation * (kernel - 1) // 2
    return nn.Sequential(nn.Conv2d(in_channels, out_channels, kernel, stride=stride, padding=pad, dilation=dilation),
                         nn.LeakyReLU(LEAK, inplace=True))


def level_widths(base: int, levels: int) -> tuple[int, ...]:
    """Channels per feature level, growing by base / 2 a level (the paper grows 16 -> 48 over five levels)."""
    return tuple(base + (base // 2) * level for level in range(levels))


class UNetFeatures(nn.Module):
    """Shared-weight U-Net: (B, 3, H, W) in [-1, 1] -> [e_0, ..., e_{L-1}], e_l (B, widths[l], H_l, W_l) float,
    H_l = ceil(H / 2^(l+1)) (stride-2 convolutions round up; the decoder resizes to each skip's size)."""

    def __init__(self, widths: tuple[int, ...]) -> None:
        super().__init__()
        ins = (3, *widths[:-1])
        self.down = nn.ModuleList(
            nn.Sequential(conv_act(cin, cout, stride=2), conv_act(cout, cout))
            for cin, cout in zip(ins, widths, strict=True)
        )
        self.up = nn.ModuleList(
            nn.Sequential(conv_act(widths[l + 1] + widths[l], widths[l]), conv_act(widths[l], widths[l]))
            for l in range(len(widths) - 1)
        )

    def forward(self, image: torch.Tensor) -> list[torch.Tensor]:
        skips = []
        x = image
        for down in self.down:
            x = down(x)
            skips.append(x)
        out = [x]
        for level in range(len(self.up) - 1, -1, -1):
            skip = skips[level]
            x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            x = self.up[level](torch.cat([x, skip], dim=1))
            out.insert(0, x)
        return out


class TileInit(nn.Module):
    """Initial fronto-parallel hypotheses of one level (paper Section 3.2).

    forward(feat_left, feat_right): (B, C, TILE h, TILE w) padded features of the level -> (hyp, soft):
        hyp (B, HYP_DIM, h, w): d = argmin of the local cost volume (full-resolution pixels), dx = dy = 0,
            p = MLP(cost at d, tile feature);
        soft (B, 1, h, w): the volume's soft-argmin in full-resolution pixels, the training signal that stands in
            for HITNet's initialisation loss (argmin itself has no gradient).
    """

    def __init__(self, channels: int, stride: int, search_range: int) -> None:
        super().__init__()
        # One 4x4 kernel for both views: stride 4 on the left, (4, 1) on the right so every column stays a candidate.
        self.tile = nn.Conv2d(channels, channels, TILE)
        self.descriptor = nn.Sequential(conv_act(1 + channels, 16, kernel=1), nn.Conv2d(16, DESC_DIM, 1))
        self.stride = stride
        self.num_disp = -(-search_range // stride)

    def forward(self, feat_left: torch.Tensor, feat_right: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        tile_left = F.leaky_relu(F.conv2d(feat_left, self.tile.weight, self.tile.bias, stride=TILE), LEAK)
        right = F.pad(feat_right, (0, TILE - 1, 0, 0), mode="replicate")
        tile_right = F.leaky_relu(F.conv2d(right, self.tile.weight, self.tile.bias, stride=(TILE, 1)), LEAK)
        volume = cost_volume(tile_left, tile_right, min(self.num_disp, tile_right.shape[-1]))
        best = volume.detach().argmin(dim=1, keepdim=True)
        desc = self.descriptor(torch.cat([volume.gather(1, best), tile_left], dim=1))
        disp = best.to(desc.dtype) * self.stride
        zeros = torch.zeros_like(disp)
        return torch.cat([disp, zeros, zeros, desc], dim=1), soft_argmin(volume) * self.stride


class ResidualDilated(nn.Module):
    """Two dilated 3x3 convs with a skip (the paper's propagation blocks): (B, C, h, w) -> (B, C, h, w)."""

    def __init__(self, channels: int, dilation: int) -> None:
        super().__init__()
        self.conv1 = conv_act(channels, channels, dilation=dilation)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=dilation, dilation=dilation)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.leaky_relu(x + self.conv2(self.conv1(x)), LEAK)


class PropagationStep(nn.Module):
    """One propagation step of one level on 1 or 2 hypotheses (paper Section 3.3).

    The CNN sees every hypothesis augmented with its warped costs and predicts an update (Delta d in feature
    pixels of the level, Delta dx, Delta dy, Delta p) for each and, for two, a confidence w each; the result is
    the softmax(w)-weighted blend of the updated hypotheses (HITNet picks the argmax; see docs/optstereo.md).

    forward(hyps, costs): lists of (B, HYP_DIM, h, w) and (B, cost_dim, h, w) -> (B, HYP_DIM, h, w).
    """

    def __init__(self, num_hyps: int, cost_dim: int, hidden: int, *, stride: int, disp_scale: float,
                 dilations: tuple[int, ...] = (1, 2, 1)) -> None:
        super().__init__()
        self.num_hyps = num_hyps
        self.stride = stride
        self.disp_scale = disp_scale
        self.inp = conv_act(num_hyps * (HYP_DIM + cost_dim), hidden, kernel=1)
        self.blocks = nn.Sequential(*(ResidualDilated(hidden, d) for d in dilations))
        self.out = nn.Conv2d(hidden, num_hyps * HYP_DIM + (num_hyps if num_hyps > 1 else 0), 3, padding=1)
        with torch.no_grad():
            self.out.weight.mul_(UPDATE_INIT_SCALE)

    def forward(self, hyps: list[torch.Tensor], costs: list[torch.Tensor]) -> torch.Tensor:
        if len(hyps) != self.num_hyps or len(costs) != self.num_hyps:
            raise ValueError(f"expected {self.num_hyps} hypotheses and costs, got {len(hyps)} and {len(costs)}")
        # d enters divided by the search range so the CNN input stays O(1) at every level.
        parts = [(h[:, :1] / self.disp_scale, h[:, 1:], c) for h, c in zip(hyps, costs, strict=True)]
        x = torch.cat([t for part in parts for t in part], dim=1)
        out = self.out(self.blocks(self.inp(x)))
        deltas = out[:, : self.num_hyps * HYP_DIM].chunk(self.num_hyps, dim=1)
        refined = [h + torch.cat([delta[:, :1] * self.stride, delta[:, 1:]], dim=1)
                   for h, delta in zip(hyps, deltas, strict=True)]
        if self.num_hyps == 1:
            return refined[0]
        weights = torch.softmax(out[:, self.num_hyps * HYP_DIM :], dim=1)
        return sum(weights[:, i : i + 1] * hyp for i, hyp in enumerate(refined))


class HITNet(nn.Module):
    """Hierarchical iterative tile refinement, coarse to fine, with OptStereo's forward contract.

    forward(left, right, iters=None, test_mode=False):
        left, right: (B, 3, H, W) float in [0, 255], H and W divisible by 8 (use
        optstereo.inference.padding.InputPadder).
        Training: a list of L - 1 + iters full-resolution disparities (B, 1, H, W), one per propagation step,
            coarse to fine (one step per coarse level, ``iters`` at the finest), positive, full-resolution pixels.
        test_mode=True: (d of the finest tiles (B, 1, H/8, W/8) in 1/8-resolution pixels, last (B, 1, H, W)),
            the same pair as OptStereo's (its finest tiles are 8 x 8 pixels).
    """

    divisor: ClassVar[int] = TILE * FINEST_STRIDE  # what optstereo.inference.padding.divisor_of reads
    #: Why optstereo.export refuses this network: a traced graph would only be valid at the example's size.
    not_exportable: ClassVar[str] = (
        "HITNet's per-level cost volume clips its disparity range to the level's width (tiles.cost_volume), a Python "
        "branch on the image size that tracing bakes in; export OptStereo, or run HITNet in torch")

    def __init__(self, *, features: UNetFeatures, inits: nn.ModuleList, steps: nn.ModuleList,
                 refine: PropagationStep, radius: int, iters: int = 2, config: HITNetConfig | None = None) -> None:
        super().__init__()
        if not len(inits) == len(steps) >= 1:
            raise ValueError(f"need one init and one step per level, got {len(inits)} and {len(steps)}")
        self.features = features
        self.inits = inits
        self.steps = steps
        self.refine = refine
        self.radius = radius
        self.iters = iters
        self.config = config

    @staticmethod
    def stride(level: int) -> int:
        """Full-resolution pixels per feature pixel of ``level``."""
        return FINEST_STRIDE * 2**level

    def forward(
        self, left: torch.Tensor, right: torch.Tensor, iters: int | None = None, test_mode: bool = False
    ) -> list[torch.Tensor] | tuple[torch.Tensor, torch.Tensor]:
        check_stereo_pair(left, right, self.divisor, next(self.parameters()).dtype)
        iters = resolve_iters(iters, self.iters)
        size = (left.shape[-2], left.shape[-1])
        feats = self.features(torch.cat([normalize_image(left), normalize_image(right)], dim=0))
        preds: list[torch.Tensor] = []
        hyp: torch.Tensor | None = None
        for level in range(len(self.inits) - 1, -1, -1):
            feat_left, feat_right = pad_to_tiles(feats[level].float()).chunk(2, dim=0)
            tile_px = TILE * self.stride(level)
            init, soft = self.inits[level](feat_left, feat_right)
            if not test_mode:
                preds.append(tiles_to_pixels(soft, tile_px, size))
            hyps = [init] if hyp is None else [upsample_hypotheses(hyp, tile_px, init.shape[-2:]), init]
            for k in range(iters if level == 0 else 1):
                step = self.steps[level] if k == 0 else self.refine
                costs = [tile_costs(feat_left, feat_right, h, self.stride(level), self.radius) for h in hyps]
                hyp = step(hyps, costs)
                hyps = [hyp]
                if not test_mode:
                    preds.append(planes_to_pixels(hyp, tile_px, size))
        assert hyp is not None  # at least one level (checked in __init__)
        if test_mode:
            return hyp[:, :1] / self.divisor, planes_to_pixels(hyp, self.divisor, size)
        return preds


def build_hitnet(cfg: HITNetConfig) -> HITNet:
    """Compose HITNet from ``cfg`` (its fields: optstereo.models.hitnet_config.HITNetConfig)."""
    cfg.validate()
    widths = level_widths(cfg.feature_channels, cfg.levels)
    cost_dim = TILE * TILE * (2 * cfg.offset_radius + 1)
    strides = [HITNet.stride(level) for level in range(cfg.levels)]
    inits = nn.ModuleList(TileInit(w, s, cfg.search_range) for w, s in zip(widths, strides, strict=True))
    # The coarsest level refines its init alone; every finer one weighs the upsampled coarse hypothesis against its own.
    steps = nn.ModuleList(
        PropagationStep(1 if level == cfg.levels - 1 else 2, cost_dim, cfg.propagation_channels, stride=s,
                        disp_scale=float(cfg.search_range))
        for level, s in enumerate(strides)
    )
    refine = PropagationStep(1, cost_dim, cfg.propagation_channels, stride=strides[0],
                             disp_scale=float(cfg.search_range))
    return HITNet(features=UNetFeatures(widths), inits=inits, steps=steps, refine=refine, radius=cfg.offset_radius,
                  iters=cfg.iters, config=cfg)
