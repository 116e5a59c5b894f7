"""Study code: baselines the PVM labels must beat, threshold sweeps and density-vs-bad-3 curves (tests, `make results`).

Methods (all on the same matcher, ``pvm_labeler.sgm.sgm_pair``, at full resolution):

- ``sgm_lr``: SGM left + right view, then the LR check (``cfg.lr_threshold``).
- ``sgm_lr_uniq``: ``sgm_lr`` plus a uniqueness-ratio filter: keep pixels whose left-view
  ``SGMResult.uniqueness`` is >= a threshold (the definition is A1's, documented in ``pvm_labeler/sgm.py``; higher
  means a more distinctive minimum). Sweeping the threshold gives its density-vs-bad-3 curve.
- ``pvm``: :func:`pvm_labeler.multiscale.label_pair`; its curve sweeps ``min_confidence`` at the configured kappas.

Metrics come from :mod:`pvm_labeler.common.metrics` (density in % of GT-valid pixels, bad-3 in %, AEPE in px,
pooled over pixels). The expensive SGM outputs can be cached under a directory (``cache_dir``) keyed by frame and by the
SGM-relevant config fields, so sweeps over kappas do not recompute them. Frames come from the shared readers
(:mod:`pvm_labeler.common.datasets`) with the evaluator's GT rule: non-occluded GT where the dataset has it, else the
most complete GT.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

import pvm_labeler
from pvm_labeler.common.atomic import atomic_path
from pvm_labeler.common.datasets import discover, load_pair
from pvm_labeler.common.errors import InputError
from pvm_labeler.common.metrics import MetricAccumulator
from pvm_labeler.config import LabelerConfig
from pvm_labeler.multiscale import RawScales, ScaleStack, label_from_scales, lr_check, run_scales, upsample_scales

logger = logging.getLogger(__name__)

#: Config fields that do not change the per-scale SGM outputs (so cached scale stacks stay valid across them).
_POST_SGM_FIELDS = ("kappa1", "kappa2", "lr_threshold", "label_mode", "upsample", "min_texture",
                    "min_confidence", "c2_scale", "extra")
#: Sources whose content determines the cached per-scale SGM outputs.
_SGM_SOURCES = ("sgm.py", "multiscale.py", "kernels/cost.py", "kernels/aggregate.py", "kernels/wta.py")


@dataclass
class Frame:
    """One evaluation frame: (H, W, 3) uint8 RGB views and (H, W) float32 GT (NaN = unknown)."""

    frame_id: str
    left: npt.NDArray[np.uint8]
    right: npt.NDArray[np.uint8]
    gt: npt.NDArray[np.float32]


def load_frames(dataset: str, root: Path | str | None, ids: Iterable[str] | None = None) -> list[Frame]:
    """GT frames of a dataset through the shared readers: noc GT where present, else the most complete GT.

    Args:
        dataset, root: as for :func:`pvm_labeler.common.datasets.discover` (e.g. ``"kitti15"``,
            ``../shared/data/kitti15``).
        ids: keep only these frames (a frame id or its prefix before ``_``, e.g. KITTI ``000046``); None = all.

    Raises:
        InputError: a file is missing or unreadable (the message names it), a requested id does not exist, or a
            frame has no GT.
    """
    refs = discover(dataset, root)
    if ids is not None:
        wanted = list(ids)
        by_id = {r.frame_id: r for r in refs} | {r.frame_id.split("_")[0]: r for r in refs}
        missing = [i for i in wanted if i not in by_id]
        if missing:
            raise InputError(f"{dataset} under {root}: no frames {missing}")
        refs = [by_id[i] for i in wanted]
    frames = []
    for ref in refs:
        sample = load_pair(ref)
        gt = sample.gt_noc if sample.gt_noc is not None else sample.gt
        if gt is None:
            raise InputError(f"{dataset} frame {ref.frame_id} has no GT ({ref.left})")
        frames.append(Frame(ref.frame_id, sample.left, sample.right, gt))
    return frames


def sgm_key(cfg: LabelerConfig) -> str:
    """Short hash of the config fields that determine the per-scale SGM outputs and of the matcher's source code
    (so a changed SGM or pyramid never reads a stale cache)."""
    values = {k: v for k, v in dataclasses.asdict(cfg).items() if k not in _POST_SGM_FIELDS}
    digest = hashlib.sha1(json.dumps(values, sort_keys=True).encode())
    package = Path(pvm_labeler.__file__).resolve().parent
    for name in _SGM_SOURCES:
        source = package / name
        digest.update(source.read_bytes() if source.is_file() else name.encode())
    return digest.hexdigest()[:12]


def raw_scales(frame: Frame, cfg: LabelerConfig, cache_dir: Path | None = None) -> RawScales:
    """``run_scales`` for one frame, read from / written to ``cache_dir/<sgm_key>/<frame_id>.npz`` if given."""
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / sgm_key(cfg) / f"{frame.frame_id}.npz"
        if path.is_file():
            with np.load(path) as data:
                n = int(data["n"])
                maps = [{key[: -len(f"_{k}")]: data[key] for key in data.files if key.endswith(f"_{k}")}
                        for k in range(n)]
                return RawScales(int(data["height"]), int(data["width"]), data["eps"], data["factors"], maps,
                                 {"pyramid": 0.0, "sgm": 0.0})
    raw = run_scales(frame.left, frame.right, cfg, frame.frame_id, uniqueness=True)
    if path is not None:
        arrays = {f"{name}_{k}": arr for k, maps in enumerate(raw.maps) for name, arr in maps.items()}
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:  # a file object: np.savez would append ".npz"
            np.savez(fh, n=len(raw.maps), height=raw.height, width=raw.width, eps=raw.eps, factors=raw.factors,
                     **arrays)
    return raw


def scale_stack(frame: Frame, cfg: LabelerConfig, cache_dir: Path | None = None) -> ScaleStack:
    """Full-resolution scale maps of one frame (SGM outputs cached under ``cache_dir`` if given)."""
    return upsample_scales(raw_scales(frame, cfg, cache_dir), cfg)


def sgm_lr_maps(stack: ScaleStack, lr_threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Full-resolution SGM + LR check from the finest scale of a stack.

    Returns:
        disp (H, W) float32 LR-checked left disparity (NaN = none), uniqueness (H, W) float32 of the left view.
    """
    if "uniqueness_l" not in stack.full_res:
        raise InputError("this scale stack has no uniqueness map: build it with compute_scales(..., uniqueness=True) "
                         "or run_scales(..., uniqueness=True) (one more pass over S, so it is off by default)")
    disp_l, _ = lr_check(stack.full_res["disp_l"], stack.full_res["disp_r"], lr_threshold)
    return disp_l, stack.full_res["uniqueness_l"]


@dataclass
class CurvePoint:
    """One point of a threshold sweep: the threshold and the pooled metrics at it."""

    threshold: float
    density: float
    bad3: float
    epe: float


def score_curve(preds: Sequence[np.ndarray], scores: Sequence[np.ndarray], gts: Sequence[np.ndarray],
                thresholds: Sequence[float]) -> list[CurvePoint]:
    """Pooled density / bad-3 / AEPE when keeping pixels with ``score >= t``, for every t (a nested filter).

    Args:
        preds: per frame (H, W) float32 disparity (NaN = none).
        scores: per frame (H, W) float32 filter score (higher = keep).
        gts: per frame (H, W) float32 GT (NaN = unknown).
        thresholds: the sweep.
    """
    n_valid = 0
    errs, scs = [], []
    for pred, score, gt in zip(preds, scores, gts, strict=True):
        valid = np.isfinite(gt)
        n_valid += int(valid.sum())
        covered = valid & np.isfinite(pred) & np.isfinite(score)
        errs.append(np.abs(pred[covered].astype(np.float64) - gt[covered]))
        scs.append(score[covered])
    err = np.concatenate(errs)
    sc = np.concatenate(scs)
    out = []
    for t in thresholds:
        keep = sc >= t
        n = int(keep.sum())
        out.append(CurvePoint(float(t), 100.0 * n / n_valid, 100.0 * float((err[keep] > 3).mean()) if n else np.nan,
                              float(err[keep].mean()) if n else np.nan))
    return out


def pvm_curve(stacks: Sequence[ScaleStack], gts: Sequence[np.ndarray], cfg: LabelerConfig,
              thresholds: Sequence[float]) -> list[CurvePoint]:
    """PVM sweep: ``cfg.min_confidence`` = t for every t in ``thresholds``, at the kappas of ``cfg``."""
    out = []
    for t in thresholds:
        c = dataclasses.replace(cfg, min_confidence=float(t))
        m = evaluate([label_from_scales(st, c).label for st in stacks], gts)
        out.append(CurvePoint(float(t), m["density"], m["bad3"], m["epe"]))
    return out


def evaluate(preds: Sequence[np.ndarray], gts: Sequence[np.ndarray]) -> dict[str, float]:
    """Pooled-over-pixels metrics (pvm_labeler.common.metrics) of several frames."""
    acc = MetricAccumulator()
    for pred, gt in zip(preds, gts, strict=True):
        acc.update(pred, gt)
    return acc.compute()


def bad3_at_density(curve: Sequence[CurvePoint], density: float) -> float:
    """bad-3 linearly interpolated along a sweep at the given density (%); NaN if the sweep never reaches it."""
    pts = sorted((p.density, p.bad3) for p in curve if np.isfinite(p.bad3))
    dens = np.array([p[0] for p in pts])
    bad = np.array([p[1] for p in pts])
    if len(pts) == 0 or density < dens[0] or density > dens[-1]:
        return float("nan")
    return float(np.interp(density, dens, bad))


#: Densities (% of GT-valid pixels) at which PVM and SGM + LR + uniqueness are compared.
MATCHED_DENSITIES = (30.0, 50.0, 70.0)


def quality_report(frames: Sequence[Frame], cfg: LabelerConfig, cache_dir: Path | None = None) -> dict:
    """PVM vs SGM + LR vs SGM + LR + uniqueness on some frames, pooled over pixels.

    Returns:
        {"pvm": metrics, "sgm_lr": metrics, "ratios": {"bad3", "density"} (PVM / SGM+LR),
         "matched": {density: {"pvm": bad3, "uniq": bad3}}, "curves": {"pvm": [...], "uniq": [...]}}.
    """
    stacks = [scale_stack(f, cfg, cache_dir) for f in frames]
    gts = [f.gt for f in frames]
    pvm = evaluate([label_from_scales(st, cfg).label for st in stacks], gts)
    base = [sgm_lr_maps(st, cfg.lr_threshold) for st in stacks]
    sgm_lr = evaluate([b[0] for b in base], gts)
    pooled_u = np.concatenate([u[np.isfinite(d)] for d, u in base])
    uniq_thr = np.unique(np.quantile(pooled_u[np.isfinite(pooled_u)], np.linspace(0.0, 0.98, 50)))
    uniq_curve = score_curve([b[0] for b in base], [b[1] for b in base], gts, uniq_thr)
    pvm_sweep = pvm_curve(stacks, gts, cfg, np.linspace(0.0, 0.5, 51))
    matched = {d: {"pvm": bad3_at_density(pvm_sweep, d), "uniq": bad3_at_density(uniq_curve, d)}
               for d in MATCHED_DENSITIES}
    return {
        "pvm": pvm, "sgm_lr": sgm_lr,
        "ratios": {"bad3": pvm["bad3"] / sgm_lr["bad3"], "density": pvm["density"] / sgm_lr["density"]},
        "matched": matched,
        "curves": {"pvm": [dataclasses.asdict(p) for p in pvm_sweep],
                   "uniq": [dataclasses.asdict(p) for p in uniq_curve]},
    }


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m pipelines.baselines``: print the KITTI 2015 quality report of the default config as JSON."""
    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--shared", type=Path, default=Path("../shared/data"), help="real data root")
    parser.add_argument("--cache", type=Path, default=None, help="cache dir for per-scale SGM outputs (e.g. /tmp)")
    parser.add_argument("--frames", default="", help="comma-separated KITTI 2015 frame ids (default: all with GT)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a LabelerConfig field (JSON value), e.g. --set kappa1=1.5")
    args = parser.parse_args(argv)
    overrides = {}
    for item in args.set:
        key, _, value = item.partition("=")
        try:
            overrides[key] = json.loads(value)
        except json.JSONDecodeError:
            overrides[key] = value
    cfg = LabelerConfig.from_dict({**dataclasses.asdict(LabelerConfig()), **overrides})
    frames = load_frames("kitti15", args.shared / "kitti15", [f for f in args.frames.split(",") if f] or None)
    report = quality_report(frames, cfg, args.cache)
    report.pop("curves")
    print(json.dumps({"config": cfg.to_dict(), **report}, indent=1, default=float))


if __name__ == "__main__":
    main()
