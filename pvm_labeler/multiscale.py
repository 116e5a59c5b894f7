"""Pyramid Voting Module: per-scale SGM for both views, variance voting and LRDCC -> semi-dense labels.

Pipeline of :func:`label_pair` (Wang et al., "PVStereo", Section III-A):

1. **Pyramid.** Scale k = 1..K uses the nominal factor ``k + eps_k`` with ``eps_k ~ U(-1, 1)``, ``eps_1 = 0``, drawn
   by :func:`draw_eps` from a generator seeded by (global seed, CRC32 of the frame id), so a frame's labels do not
   depend on worker order. Sizes are rounded (``w_k = round(W / f)``), so the TRUE horizontal factor ``W / w_k`` is
   what scales disparities. Downsampling uses ``cv2.INTER_AREA`` (a box filter over the exact source footprint):
   it anti-aliases, so the census transform at coarse scales sees a faithful low-pass image rather than aliased
   texture.
2. **Per-scale SGM**, left and right views from one cost volume (``pvm_labeler.sgm.sgm_pair``), search range
   ``ceil(max_disp / factor)``.
3. **Upsampling** of each scale's disparity (multiplied by the true factor) and normalized inverse cost c to full
   resolution with BILINEAR interpolation (``cv2.INTER_LINEAR``, pixel-centre aligned like INTER_AREA). Bilinear
   keeps slanted surfaces (roads) planar across scales; nearest neighbour produces staircases of up to ``factor``
   pixels whose std over scales exceeds kappa1, which loses about a quarter of the labels (see docs/pvm.md). A NaN
   poisons every output pixel whose 2x2 footprint touches it, which is the conservative choice for voting.
4. **Voting** (``kernels/vote.py``): C1 = std_k D^k, C2 = std_k c^k, keep iff C1 < kappa1, C2 < kappa2 and every
   scale is valid. Done for the left and the right view. Beyond the paper, kept pixels whose continuous confidence
   is below ``cfg.min_confidence`` and pixels with a constant census window (``cfg.min_texture``) are dropped.
5. **LRDCC** (``kernels/lrcheck.py``) between the voted left and right maps (rounded look-up, ``cfg.lr_threshold``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
import zlib
from dataclasses import dataclass, field

import cv2
import numpy as np
import numpy.typing as npt

from pvm_labeler.common.errors import ConfigError, InputError
from pvm_labeler.config import LabelerConfig
from pvm_labeler.stages import stage_codes
from pvm_labeler.voting import lr_check, vote  # re-exported: the stages' public home stays multiscale

logger = logging.getLogger(__name__)

_UPSAMPLE_FLAGS = {"linear": cv2.INTER_LINEAR, "nearest": cv2.INTER_NEAREST}


@dataclass
class LabelResult:
    """Output of :func:`label_pair`.

    Attributes:
        label: (H, W) float32 left-view semi-dense label, NaN = no label.
        label_right: (H, W) float32 right-view consistent label (right(x) matches left(x + d)), NaN = no label.
        confidence: (H, W) float32 in [0, 1], ``mean_k c^k * (1 - C1 / kappa1) * (1 - C2 / c2_scale)`` on labelled
            pixels, 0 where there is no label.
        eps: (K,) float64 eps_k per scale (eps_1 = 0).
        factors: (K,) float64 true horizontal downsampling factor ``W / w_k`` per scale (after rounding sizes).
        timings: seconds per stage: "pyramid", "sgm", "upsample", "vote", "lrcheck", "total".
        intermediates: on request: "disp_l", "conf_l", "disp_r", "conf_r" (K, H, W) float32 full-resolution scale
            maps; "C1", "C2", "C1_right", "C2_right" (H, W) float32; "V" (H, W) uint8 vote count (2 where some scale
            is invalid); "voted", "voted_right" (H, W) float32 maps after the vote and the confidence/texture filters,
            before the LR check.
        stages: (candidate (H, W) float32 vote without rejection, codes (H, W) uint8 into
            ``pvm_labeler.stages.GROUPS``): which stage removed each left-view pixel (the vote table).
    """

    label: npt.NDArray[np.float32]
    label_right: npt.NDArray[np.float32]
    confidence: npt.NDArray[np.float32]
    eps: npt.NDArray[np.float64]
    factors: npt.NDArray[np.float64]
    timings: dict[str, float] = field(default_factory=dict)
    stages: tuple[np.ndarray, np.ndarray] | None = None
    intermediates: dict[str, np.ndarray] | None = None


@dataclass
class ScaleStack:
    """Per-scale SGM outputs of both views brought to full resolution (the expensive, kappa-independent part).

    Attributes:
        disp_l, conf_l, disp_r, conf_r: (K, H, W) float32, NaN = invalid.
        eps: (K,) float64.
        factors: (K,) float64 true horizontal factors.
        timings: seconds for "pyramid", "sgm", "upsample".
        full_res: the finest scale's raw SGM maps "disp_l", "disp_r", "uniqueness_l" (H, W) float32 (the last only
            when computed with ``uniqueness=True``), used by
            the SGM + LR (+ uniqueness) baselines in pipelines.baselines; and "range_l", "range_r" (H, W) uint8
            grey-level range (max - min) over the census window of each view (the texture test).
    """

    disp_l: npt.NDArray[np.float32]
    conf_l: npt.NDArray[np.float32]
    disp_r: npt.NDArray[np.float32]
    conf_r: npt.NDArray[np.float32]
    eps: npt.NDArray[np.float64]
    factors: npt.NDArray[np.float64]
    timings: dict[str, float] = field(default_factory=dict)
    full_res: dict[str, np.ndarray] = field(default_factory=dict)


def draw_eps(seed: int, frame_id: str, k: int) -> npt.NDArray[np.float64]:
    """Scale jitter eps_k ~ U(-1, 1) for k = 2..K (eps_1 = 0), reproducible per (seed, frame id).

    The generator is seeded with ``[seed mod 2**64, crc32(frame_id)]``: CRC32 is stable across processes, unlike
    Python's salted ``hash()``, so any worker labels a frame identically.

    Returns:
        (K,) float64.
    """
    if k < 1:
        raise ConfigError(f"k must be >= 1, got {k}")
    key = zlib.crc32(str(frame_id).encode("utf-8"))
    gen = np.random.default_rng([int(seed) % 2**64, key])
    eps = gen.uniform(-1.0, 1.0, size=k)
    eps[0] = 0.0
    return eps


def scale_geometry(height: int, width: int, eps: np.ndarray, max_disp: int) -> list[tuple[int, int, float, int]]:
    """Rounded size, true horizontal factor and search range of every scale.

    Returns:
        One ``(h_k, w_k, factor_k, max_disp_k)`` per scale: ``w_k = round(W / (k + eps_k))`` (>= 1),
        ``factor_k = W / w_k`` and ``max_disp_k = ceil(max_disp / factor_k)``.
    """
    out = []
    for idx, e in enumerate(eps):
        nominal = (idx + 1) + float(e)
        h_k = max(1, int(round(height / nominal)))
        w_k = max(1, int(round(width / nominal)))
        factor = width / w_k
        # The 1e-9 guards against ceil(12.000000001) = 13 from float noise when the ratio is an integer.
        d_k = max(1, math.ceil(max_disp / factor - 1e-9))
        out.append((h_k, w_k, factor, d_k))
    return out


def scale_cells(scale: tuple[int, int, float, int]) -> int:
    """Cost-volume cells h_k * w_k * D_k of one :func:`scale_geometry` entry: the relative SGM cost of that scale."""
    h_k, w_k, _, d_k = scale
    return h_k * w_k * d_k


def _to_grey(image: np.ndarray, name: str) -> np.ndarray:
    if not isinstance(image, np.ndarray):
        raise InputError(f"{name} must be a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise InputError(f"{name} must be uint8, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
    if image.ndim == 2:
        return np.ascontiguousarray(image)
    raise InputError(f"{name} must be (H, W, 3) RGB or (H, W) grey uint8, got shape {image.shape}")


def check_sizes(height: int, width: int, geometry: list[tuple[int, int, float, int]], cfg: LabelerConfig) -> None:
    """Every scale must search >= 2 disparities, be wider than its search range plus the census window, and taller
    than the window."""
    margin = cfg.census_window
    for idx, (h_k, w_k, factor, d_k) in enumerate(geometry):
        if d_k < 2:  # the SGM needs two disparities to choose from
            raise InputError(f"max_disp={cfg.max_disp} too small for k={cfg.k}: scale {idx + 1} (factor {factor:.2f}) "
                             f"would search {d_k} disparity; every scale needs >= 2, so raise max_disp or lower k")
        if w_k <= d_k + margin or h_k <= margin:
            # Worst case over eps is factor K + 1; this width always works for the given K and max_disp.
            need_w = math.ceil((cfg.k + 1) * (margin + 2)) + cfg.max_disp
            raise InputError(
                f"image {width}x{height} too small for k={cfg.k} and max_disp={cfg.max_disp}: scale {idx + 1} "
                f"(factor {factor:.2f}) is {w_k}x{h_k} px with a search range of {d_k} px; every scale needs "
                f"width > search range + census window ({margin}) and height > {margin}. Use a width >= {need_w} "
                f"and height >= {(cfg.k + 1) * (margin + 1)}, or lower k / max_disp."
            )


@dataclass
class RawScales:
    """Per-scale SGM outputs at their own (coarse) resolution, before upsampling.

    Attributes:
        height, width: full-resolution size.
        eps: (K,) float64; factors: (K,) float64 true horizontal factors.
        maps: per scale k a dict "disp_l", "conf_l", "disp_r", "conf_r" of (h_k, w_k) float32 maps (disparities in
            scale-k pixels); scale 1 also has the texture maps "range_l", "range_r" and, on request, "uniqueness_l".
        timings: seconds for "pyramid" and "sgm".
    """

    height: int
    width: int
    eps: npt.NDArray[np.float64]
    factors: npt.NDArray[np.float64]
    maps: list[dict[str, np.ndarray]]
    timings: dict[str, float] = field(default_factory=dict)


def run_scales(left: np.ndarray, right: np.ndarray, cfg: LabelerConfig, frame_id: str,
               uniqueness: bool = False) -> RawScales:
    """Validate the inputs, build the pyramid and run SGM for both views at every scale.

    Args:
        left, right: (H, W, 3) uint8 RGB or (H, W) uint8 grey, same shape.
        cfg: labeler config (k, max_disp, seed, SGM settings).
        frame_id: stable frame name; seeds eps together with cfg.seed.
        uniqueness: also keep the full-resolution left view's uniqueness ratio (``maps[0]["uniqueness_l"]``, for
            the uniqueness-filter baseline); the labels do not use it.

    Raises:
        InputError: wrong dtype/shape, different sizes, or an image too small for K and max_disp.
        ConfigError: invalid config values.
    """
    from pvm_labeler.sgm import sgm_pair  # noqa: PLC0415  (keeps the vote/LR wrappers importable without the SGM)

    cfg = _validated(cfg)
    t0 = time.perf_counter()
    grey_l = _to_grey(left, "left")
    grey_r = _to_grey(right, "right")
    if grey_l.shape != grey_r.shape:
        raise InputError(f"left/right sizes differ: {grey_l.shape} vs {grey_r.shape} for frame {frame_id}")
    height, width = grey_l.shape
    if cfg.max_disp >= width:
        raise InputError(f"max_disp={cfg.max_disp} must be smaller than the image width {width} (frame {frame_id})")
    eps = draw_eps(cfg.seed, frame_id, cfg.k)
    geometry = scale_geometry(height, width, eps, cfg.max_disp)
    check_sizes(height, width, geometry, cfg)
    pyramid = []
    for h_k, w_k, _, _ in geometry:
        if (h_k, w_k) == (height, width):
            pyramid.append((grey_l, grey_r))
        else:
            pyramid.append((cv2.resize(grey_l, (w_k, h_k), interpolation=cv2.INTER_AREA),
                            cv2.resize(grey_r, (w_k, h_k), interpolation=cv2.INTER_AREA)))
    t1 = time.perf_counter()
    maps: list[dict[str, np.ndarray]] = [{} for _ in geometry]
    # Cheapest scale first, full resolution last (the scales are independent: the order changes no label).
    for idx in sorted(range(len(geometry)), key=lambda i: scale_cells(geometry[i])):
        (img_l, img_r), (_, _, _, d_k) = pyramid[idx], geometry[idx]
        res_l, res_r = sgm_pair(img_l, img_r, cfg, max_disp=d_k, right_view=True, uniqueness=uniqueness and idx == 0)
        maps[idx] = {"disp_l": res_l.disp, "conf_l": res_l.conf, "disp_r": res_r.disp, "conf_r": res_r.conf}
        if idx == 0:  # eps_1 = 0: scale 1 is the full-resolution SGM, whose uniqueness the baselines use
            if res_l.uniqueness is not None:
                maps[0]["uniqueness_l"] = res_l.uniqueness
            maps[0]["range_l"] = _window_range(img_l, cfg.census_window)
            maps[0]["range_r"] = _window_range(img_r, cfg.census_window)
    timings = {"pyramid": t1 - t0, "sgm": time.perf_counter() - t1}
    return RawScales(height, width, eps, np.array([g[2] for g in geometry]), maps, timings)


def upsample_scales(raw: RawScales, cfg: LabelerConfig) -> ScaleStack:
    """Bring every scale to full resolution (disparity times the true factor) with ``cfg.upsample`` interpolation.

    Returns:
        ScaleStack with (K, H, W) float32 maps of both views (memory: 4 x K x H x W x 4 bytes, 45 MB for KITTI, K=6).
    """
    t0 = time.perf_counter()
    n = len(raw.maps)
    names = ("disp_l", "conf_l", "disp_r", "conf_r")
    stacks = {name: np.empty((n, raw.height, raw.width), dtype=np.float32) for name in names}
    interp = _UPSAMPLE_FLAGS[cfg.upsample]
    for idx, (maps, factor) in enumerate(zip(raw.maps, raw.factors, strict=True)):
        for name in names:
            _upsample_into(maps[name], stacks[name][idx], interp, factor if name.startswith("disp") else 1.0)
    timings = dict(raw.timings, upsample=time.perf_counter() - t0)
    full_res = {name: raw.maps[0][name] for name in ("disp_l", "disp_r", "uniqueness_l", "range_l", "range_r")
                if name in raw.maps[0]}
    return ScaleStack(eps=raw.eps, factors=raw.factors, timings=timings, full_res=full_res, **stacks)


def compute_scales(left: np.ndarray, right: np.ndarray, cfg: LabelerConfig, frame_id: str,
                   uniqueness: bool = False) -> ScaleStack:
    """:func:`run_scales` then :func:`upsample_scales` (the expensive, kappa-independent part of label_pair)."""
    return upsample_scales(run_scales(left, right, cfg, frame_id, uniqueness), cfg)


def _window_range(grey: np.ndarray, window: int) -> np.ndarray:
    """(H, W) uint8 max - min of ``grey`` over the window x window neighbourhood (replicated border)."""
    kernel = np.ones((window, window), np.uint8)
    hi = cv2.dilate(grey, kernel, borderType=cv2.BORDER_REPLICATE)
    lo = cv2.erode(grey, kernel, borderType=cv2.BORDER_REPLICATE)
    return cv2.subtract(hi, lo)


def _upsample_into(values: np.ndarray, out: np.ndarray, interp: int, scale: float) -> None:
    """Resize (h, w) float32 ``values`` into the preallocated (H, W) float32 ``out`` and multiply by ``scale``."""
    if values.shape == out.shape:
        np.copyto(out, values)
    else:
        cv2.resize(np.ascontiguousarray(values, dtype=np.float32), (out.shape[1], out.shape[0]), dst=out,
                   interpolation=interp)
    if scale != 1.0:
        np.multiply(out, np.float32(scale), out=out)


def label_from_scales(stack: ScaleStack, cfg: LabelerConfig, return_intermediates: bool = False,
                      with_stages: bool = False) -> LabelResult:
    """Voting (both views) and LRDCC on precomputed scale maps; cheap, so kappa sweeps reuse one ScaleStack.

    ``with_stages`` also fills ``LabelResult.stages`` (one more vote pass: only worth it where GT will score it).
    """
    cfg = _validated(cfg)
    if stack.disp_l.shape[0] != cfg.k:
        raise ConfigError(f"scale stack has {stack.disp_l.shape[0]} scales but cfg.k={cfg.k}")
    t0 = time.perf_counter()
    voted_l, conf_l, c1_l, c2_l = vote(stack.disp_l, stack.conf_l, cfg, stack.factors)
    voted_r, conf_r, c1_r, c2_r = vote(stack.disp_r, stack.conf_r, cfg, stack.factors)
    if cfg.min_confidence > 0:
        # Beyond the paper: the continuous confidence ranks pixels better than the two hard votes alone (docs/pvm.md).
        voted_l[conf_l < cfg.min_confidence] = np.nan
        voted_r[conf_r < cfg.min_confidence] = np.nan
    if cfg.min_texture > 0:
        # A constant census window has census code 0 in both views, so every disparity costs 0 there: SGM only
        # propagates values into such pixels from their surroundings, consistently at every scale, and the vote
        # cannot see it. These pixels carry no matching evidence of their own.
        voted_l[stack.full_res["range_l"] < cfg.min_texture] = np.nan
        voted_r[stack.full_res["range_r"] < cfg.min_texture] = np.nan
    t1 = time.perf_counter()
    label, label_right = lr_check(voted_l, voted_r, cfg.lr_threshold)
    confidence = np.where(np.isfinite(label), conf_l, np.float32(0.0)).astype(np.float32)
    stages = None
    if with_stages:
        free = dataclasses.replace(cfg, kappa1=np.inf, kappa2=np.inf)  # the candidate: the vote with no rejection
        candidate = vote(stack.disp_l, stack.conf_l, free, stack.factors)[0]
        stages = (candidate, stage_codes(candidate, c1_l, c2_l, conf_l, stack.full_res["range_l"], label,
                                         cfg.kappa1, cfg.kappa2, cfg.min_confidence, cfg.min_texture))
    t2 = time.perf_counter()
    timings = dict(stack.timings)
    timings.update(vote=t1 - t0, lrcheck=t2 - t1)
    intermediates = None
    if return_intermediates:
        with np.errstate(invalid="ignore"):
            votes = (c1_l >= cfg.kappa1).astype(np.uint8) + (c2_l >= cfg.kappa2).astype(np.uint8)
        votes[~np.isfinite(c1_l)] = 2
        intermediates = {
            "disp_l": stack.disp_l, "conf_l": stack.conf_l, "disp_r": stack.disp_r, "conf_r": stack.conf_r,
            "C1": c1_l, "C2": c2_l, "C1_right": c1_r, "C2_right": c2_r, "V": votes,
            "voted": voted_l, "voted_right": voted_r,
        }
    return LabelResult(label=label, label_right=label_right, confidence=confidence, eps=stack.eps,
                       factors=stack.factors, timings=timings, intermediates=intermediates, stages=stages)


def label_pair(
    left: np.ndarray, right: np.ndarray, cfg: LabelerConfig, frame_id: str, return_intermediates: bool = False,
    with_stages: bool = False,
) -> LabelResult:
    """PVM pseudo-label of one rectified stereo pair.

    Args:
        left, right: (H, W, 3) uint8 RGB or (H, W) uint8 grey, same shape.
        cfg: labeler config; defaults are the values measured best on KITTI 2015 (docs/pvm.md).
        frame_id: stable frame name (with cfg.seed it fixes the pyramid jitter eps).
        return_intermediates: also return per-scale maps and C1/C2/V (memory: 4 x K x H x W float32).

    Returns:
        LabelResult (label, label_right, confidence, eps, factors, timings, intermediates).

    Raises:
        InputError: bad dtype/shape, mismatched sizes, image too small for K and max_disp.
        ConfigError: invalid config values.
    """
    t0 = time.perf_counter()
    if not isinstance(frame_id, str):  # None seeded the jitter as the string "None", like every other None
        raise InputError(f"frame_id must be the pair's name (a str: it seeds the jitter), got {frame_id!r}")
    if 0 in np.shape(left)[:2] or 0 in np.shape(right)[:2]:  # an OpenCV assertion from deep inside otherwise
        raise InputError(f"empty image: left {np.shape(left)}, right {np.shape(right)}")
    stack = compute_scales(left, right, cfg, frame_id)
    result = label_from_scales(stack, cfg, return_intermediates, with_stages)
    result.timings["total"] = time.perf_counter() - t0
    logger.debug("frame %s: %s", frame_id, {k: round(v, 4) for k, v in result.timings.items()})
    return result


def _validated(cfg: LabelerConfig) -> LabelerConfig:
    if not isinstance(cfg, LabelerConfig):
        raise ConfigError(f"cfg must be a LabelerConfig, got {type(cfg).__name__}")
    return cfg.validate()
