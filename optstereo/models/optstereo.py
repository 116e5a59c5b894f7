"""OptStereo (paper Section III-B), composed from injected parts.

Paper symbol -> module:
    F_l, F_r (1/8, C = 256)          FeatureEncoder (extractor.py), shared weights, on [I_l; I_r] (per image on CPU)
    M0..M3, lookup U(j'/2^k)_d, M_l  CorrBlock1D (correlation.py)
    h^0                               HiddenInit (update.py): tanh(conv3x3(F_l))
    eq. (GRU), x^k = [D, M_l, F_l]   ConvGRU (update.py), F_l part precomputed once per forward
    Delta D                           DispHead (update.py)
    upsampling module, D^k            ConvUpsampler (paper) or ConvexUpsampler (upsample.py)
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import ClassVar

import torch
from torch import nn

from optstereo.models.config import ModelConfig
from optstereo.models.correlation import CorrBlock1D
from optstereo.models.update import ConvGRU

DIVISOR = 8  # stride of the feature extractor: inputs must have H, W divisible by it
CHUNK_MIN_PIXELS = 256 * 256  # CPU: encoder and upsampler one image per call from this size on (_chunk_size)


def normalize_image(image: torch.Tensor) -> torch.Tensor:
    """[0, 255] -> [-1, 1]: 2 * (x / 255) - 1, the same for both views and every dataset."""
    return image * (2.0 / 255.0) - 1.0


def check_stereo_pair(left: torch.Tensor, right: torch.Tensor, divisor: int,
                      weights: torch.dtype = torch.float32) -> None:
    """Raise ValueError (with the actual shapes) unless left, right are equal (B, 3, H, W) with H, W % divisor == 0,
    and TypeError for a dtype the network's ``weights`` cannot take (float64 but for a ``.double()`` model, complex,
    bool)."""
    for tensor in (left, right):
        if (tensor.dtype == torch.float64 and weights != torch.float64) or tensor.dtype == torch.bool \
                or tensor.dtype.is_complex:
            raise TypeError(f"left/right must be {str(weights)[6:]} (or uint8, half) tensors of 0-255 values for "
                            f"this {str(weights)[6:]} network, got {tensor.dtype}"
                            f"{'; pass .float()' if tensor.dtype == torch.float64 else ''}")
    if left.ndim != 4 or right.ndim != 4:
        raise ValueError(f"left/right must be 4-D (B, 3, H, W), got {tuple(left.shape)} and {tuple(right.shape)}")
    if left.shape != right.shape:
        raise ValueError(f"left/right shapes differ: {tuple(left.shape)} vs {tuple(right.shape)}")
    if left.shape[1] != 3:
        raise ValueError(f"left/right must have 3 channels (B, 3, H, W), got {tuple(left.shape)}")
    h, w = left.shape[-2:]
    if h % divisor or w % divisor:
        raise ValueError(f"H, W must be divisible by {divisor}, got ({h}, {w}); "
                             "pad with optstereo.inference.padding.InputPadder")


def resolve_iters(iters: int | None, default: int) -> int:
    """The iteration count of one forward: ``iters``, or the model's ``default`` when None; ValueError below 1."""
    iters = default if iters is None else iters
    if iters < 1:
        raise ValueError(f"iters must be >= 1, got {iters}")
    return iters


class OptStereo(nn.Module):
    """Iterative 1-D stereo network of PVStereo.

    forward(left, right, iters=None, test_mode=False):
        left, right: (B, 3, H, W) float in [0, 255], H and W divisible by 8 (use
        optstereo.inference.padding.InputPadder).
        Training: returns a list of N_s full-resolution disparities D^1..D^{N_s}, each (B, 1, H, W), positive
            (left(x) matches right(x - d)), in full-resolution pixels.
        test_mode=True: returns (D_s^{N_s} (B, 1, H/8, W/8) in 1/8-resolution pixels, D^{N_s} (B, 1, H, W));
            only the last iteration is upsampled.
        features: (2B, C, H/8, W/8) = [F_l; F_r], the encoder's output for (left, right) computed beforehand (a
            cache of fixed crops, pipelines/studies/recipe_table.py); None = run the encoder. The images are
            still needed (the upsampler reads I_l).

    ``freeze_encoder()`` fixes the feature encoder for training: no gradient, run under ``torch.no_grad`` (no
    activations kept), and kept in eval mode by ``train()`` (batch-norm running statistics stay as loaded).
    """

    divisor: ClassVar[int] = DIVISOR  # what optstereo.inference.padding.divisor_of reads to pad inputs for this network

    def __init__(
        self,
        *,
        feature_encoder: nn.Module,
        corr_block: CorrBlock1D,
        hidden_init: nn.Module,
        update_block: ConvGRU,
        disp_head: nn.Module,
        upsampler: nn.Module,
        iters: int = 8,
        config: ModelConfig | None = None,
        image_chunk: int | None = None,
    ) -> None:
        super().__init__()
        self.feature_encoder = feature_encoder
        self.corr_block = corr_block
        self.hidden_init = hidden_init
        self.update_block = update_block
        self.disp_head = disp_head
        self.upsampler = upsampler
        self.iters = iters
        self.config = config
        self.image_chunk = image_chunk
        # Batch statistics tie the images of a batch together; every other normalisation is per image.
        self._per_image_encoder = not any(isinstance(m, nn.modules.batchnorm._BatchNorm)
                                          for m in feature_encoder.modules())
        self.encoder_frozen = False  # a training choice (optim.freeze_encoder), not part of the weights

    def freeze_encoder(self) -> OptStereo:
        """Fix the feature encoder: requires_grad False, forward under no_grad, eval mode whatever ``train()`` says."""
        self.encoder_frozen = True
        self.feature_encoder.requires_grad_(False)
        self.feature_encoder.eval()
        return self

    def train(self, mode: bool = True) -> OptStereo:
        """nn.Module.train, except that a frozen encoder stays in eval mode (its batch norms keep their statistics)."""
        super().train(mode)
        if self.encoder_frozen:
            self.feature_encoder.eval()
        return self

    def _chunk_size(self, images: torch.Tensor) -> int:
        """Images per call of the full- and half-resolution modules (encoder, upsampler); 0 = all at once.

        ``image_chunk``: None = automatic: 1 on CPU for images of at least CHUNK_MIN_PIXELS (the result is the
        same; one image's high-resolution activations stay in cache far better), else 0 (GPUs and small crops
        prefer one big call). With batch norm in the encoder chunking would change its statistics, so it is never
        done there. Measured, paper-size model, train step batch 2, 2 threads, per image vs one call: 320x736
        9.34 vs 11.95 s (encoder only), 192x384 3.09 vs 3.16 s, 128x256 1.58 vs 1.56 s; the conv upsampler's 8
        full-resolution calls of a 320x736 batch-2 step 1.10 vs 1.61 s (forward + backward).
        """
        chunk = self.image_chunk
        if chunk is None:
            large = images.shape[-2] * images.shape[-1] >= CHUNK_MIN_PIXELS
            chunk = 1 if images.device.type == "cpu" and large else 0
        return chunk

    @staticmethod
    def _in_chunks(fn: Callable[..., torch.Tensor], chunk: int, *tensors: torch.Tensor) -> torch.Tensor:
        """fn(*tensors), evaluated ``chunk`` samples at a time along dim 0 and concatenated (0 = one call)."""
        if chunk <= 0 or tensors[0].shape[0] <= chunk:
            return fn(*tensors)
        parts = zip(*(t.split(chunk) for t in tensors), strict=True)
        return torch.cat([fn(*part) for part in parts])

    def _encode(self, images: torch.Tensor) -> torch.Tensor:
        """F for a stack of images (2B, 3, H, W) -> (2B, C, H/8, W/8), per image on CPU (see _chunk_size)."""
        chunk = self._chunk_size(images) if self._per_image_encoder else 0
        with torch.no_grad() if self.encoder_frozen else contextlib.nullcontext():
            return self._in_chunks(self.feature_encoder, chunk, images)

    def _upsample(self, disp: torch.Tensor, hidden: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        """D^k (B, 1, H, W) from D_s^k, h^k and I_l, per image on CPU (see _chunk_size)."""
        return self._in_chunks(self.upsampler, self._chunk_size(image), disp, hidden, image)

    @property
    def min_width(self) -> int:
        """Narrowest input width (pixels) the cost-volume pyramid takes: every level keeps at least one column."""
        return DIVISOR * self.corr_block.min_width

    def _check_inputs(self, left: torch.Tensor, right: torch.Tensor) -> None:
        check_stereo_pair(left, right, self.divisor, next(self.parameters()).dtype)
        w = left.shape[-1]
        if w < self.min_width:
            raise ValueError(f"W must be >= {self.min_width} for {self.corr_block.num_levels} cost-volume levels, "
                             f"got W = {w}")

    def forward(
        self, left: torch.Tensor, right: torch.Tensor, iters: int | None = None, test_mode: bool = False,
        disp_init: torch.Tensor | None = None, features: torch.Tensor | None = None,
    ) -> list[torch.Tensor] | tuple[torch.Tensor, torch.Tensor]:
        """``disp_init``: (B, 1, H/8, W/8) start D_s^0 in 1/8-grid pixels (a coarse-to-fine start,
        optstereo.inference.cascade), detached; None = the paper's zero start. ``features``: see the class."""
        self._check_inputs(left, right)
        iters = resolve_iters(iters, self.iters)
        image_left = normalize_image(left)
        if features is None:
            feats = self._encode(torch.cat([image_left, normalize_image(right)], dim=0))
        else:
            b, _, h, w = left.shape
            if features.ndim != 4 or (features.shape[0], *features.shape[-2:]) != (2 * b, h // DIVISOR, w // DIVISOR):
                raise ValueError(f"features must be [F_l; F_r] (2B, C, H/8, W/8) with (2B, H/8, W/8) = "
                                 f"{(2 * b, h // DIVISOR, w // DIVISOR)}, got {tuple(features.shape)}")
            feats = features.to(left.device)
        feat_left, feat_right = feats.chunk(2, dim=0)

        pyramid = self.corr_block.build_pyramid(feat_left, feat_right)
        hidden = self.hidden_init(feat_left)
        static = self.update_block.precompute(feat_left)
        b, _, h8, w8 = feat_left.shape
        # D_s is accumulated in float32 even under autocast: bf16 has ~3 significant digits.
        disp = torch.zeros(b, 1, h8, w8, device=left.device, dtype=torch.float32)  # D_s^0 = 0
        if disp_init is not None:
            if tuple(disp_init.shape) != (b, 1, h8, w8):
                raise ValueError(f"disp_init must be (B, 1, H/8, W/8) = {(b, 1, h8, w8)}, got {tuple(disp_init.shape)}")
            disp = disp_init.detach().float().to(left.device)  # no gradient into the pass that made it

        preds: list[torch.Tensor] = []
        for k in range(iters):
            # Detached before the lookup as in RAFT: the gradient of D^k flows through Delta D^k only.
            disp = disp.detach()
            corr = self.corr_block.lookup(pyramid, disp)
            hidden = self.update_block(hidden, torch.cat([disp, corr], dim=1).to(hidden.dtype), static)
            disp = disp + self.disp_head(hidden).float()
            if test_mode and k < iters - 1:
                continue
            preds.append(self._upsample(disp, hidden, image_left))
        if test_mode:
            return disp, preds[-1]
        return preds
