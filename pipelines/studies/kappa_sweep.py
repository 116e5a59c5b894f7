"""Sweep PVM's voting thresholds kappa1 x kappa2 on a dataset and draw the density-vs-error trade-off.

This is the paper's PVM ablation figure: each (kappa1, kappa2) gives one label density and one error, pooled over
the pixels of all frames. The per-scale SGM (the expensive, kappa-independent part) runs once per frame
(``multiscale.compute_scales``); only voting + LRDCC are redone per threshold pair (``label_from_scales``). The
full-resolution SGM + LR check of the same matcher is drawn as a reference point.

GT: the non-occluded map where the dataset has one (KITTI disp_noc), else the most complete GT.

Usage::

    python -m pipelines.studies.kappa_sweep --dataset kitti15 --root ../shared/data/kitti15 --out out/kappa_sweep
    python -m pipelines.studies.kappa_sweep --dataset sample --k 4 --max-disp 64 --kappa1 0.5,1,2 --kappa2 0.05,0.1

Writes ``sweep.json``, ``sweep.md`` and ``kappa_tradeoff.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import time
from pathlib import Path
from typing import Any

from pvm_labeler.common.datasets import DATASETS, discover, load_pair
from pvm_labeler.common.metrics import MetricAccumulator
from pvm_labeler.config import LabelerConfig

logger = logging.getLogger("pipelines.studies.kappa_sweep")

DEFAULT_KAPPA1 = (0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 5.0)
DEFAULT_KAPPA2 = (0.02, 0.04, 0.08, 0.12, 0.2)


def sweep(
    dataset: str,
    root: Path | None,
    cfg: LabelerConfig,
    kappa1: tuple[float, ...],
    kappa2: tuple[float, ...],
    limit: int | None = None,
    split: str = "training",
) -> dict[str, Any]:
    """Pooled metrics for every (kappa1, kappa2) and for full-resolution SGM + LR.

    Returns:
        dict with ``points`` (list of {kappa1, kappa2, density, bad1, bad3, epe, ...}), ``sgm_lr`` (metrics),
        ``frames`` (ids), ``config`` (base config), ``seconds``.
    """
    from pvm_labeler.multiscale import compute_scales, label_from_scales, lr_check

    refs = discover(dataset, root, split)[:limit]
    accs = {(k1, k2): MetricAccumulator() for k1 in kappa1 for k2 in kappa2}
    base_acc = MetricAccumulator()
    t0 = time.perf_counter()
    for i, ref in enumerate(refs):
        sample = load_pair(ref)
        gt = sample.gt_noc if sample.gt_noc is not None else sample.gt
        if gt is None:
            logger.warning("%s has no GT; skipped", ref.frame_id)
            continue
        stack = compute_scales(sample.left, sample.right, cfg, ref.frame_id)
        for (k1, k2), acc in accs.items():
            result = label_from_scales(stack, dataclasses.replace(cfg, kappa1=k1, kappa2=k2))
            acc.update(result.label, gt)
        sgm_lr, _ = lr_check(stack.full_res["disp_l"], stack.full_res["disp_r"], cfg.lr_threshold)
        base_acc.update(sgm_lr, gt)
        logger.info("frame %d/%d %s done (%.0f s)", i + 1, len(refs), ref.frame_id, time.perf_counter() - t0)
    points = [{"kappa1": k1, "kappa2": k2, **acc.compute()} for (k1, k2), acc in accs.items()]
    return {"dataset": dataset, "frames": [r.frame_id for r in refs], "config": cfg.to_dict(), "points": points,
            "sgm_lr": base_acc.compute(), "seconds": time.perf_counter() - t0}


def plot(result: dict[str, Any], path: Path) -> Path:
    """Density vs bad-3 and vs AEPE: one curve per kappa2 (points along kappa1), SGM + LR as a star."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    kappa2s = sorted({p["kappa2"] for p in result["points"]})
    for ax, (key, label) in zip(axes, (("bad3", "bad-3 (%)"), ("epe", "AEPE (px)")), strict=True):
        for k2 in kappa2s:
            pts = sorted((p for p in result["points"] if p["kappa2"] == k2), key=lambda p: p["kappa1"])
            ax.plot([p["density"] for p in pts], [p[key] for p in pts], "o-", label=f"kappa2={k2}")
            for p in pts:
                ax.annotate(f"{p['kappa1']:g}", (p["density"], p[key]), fontsize=6, xytext=(2, 2),
                            textcoords="offset points")
        base = result["sgm_lr"]
        ax.plot([base["density"]], [base[key]], "k*", markersize=12, label="SGM + LR (full res)")
        ax.set_xlabel("label density (% of GT-valid px)")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    cfg = result["config"]
    fig.suptitle(f"PVM trade-off on {result['dataset']} ({len(result['frames'])} frames, K={cfg['k']}, "
                 f"max_disp={cfg['max_disp']}); point labels = kappa1 (px)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def markdown(result: dict[str, Any]) -> str:
    lines = ["| kappa1 (px) | kappa2 | density % | bad-1 % | bad-3 % | AEPE px | D1 % |",
             "|---:|---:|---:|---:|---:|---:|---:|"]
    for p in sorted(result["points"], key=lambda p: (p["kappa2"], p["kappa1"])):
        lines.append(f"| {p['kappa1']:g} | {p['kappa2']:g} | {p['density']:.1f} | {p['bad1']:.2f} | "
                     f"{p['bad3']:.2f} | {p['epe']:.3f} | {p['d1']:.2f} |")
    b = result["sgm_lr"]
    lines.append(f"| SGM + LR | - | {b['density']:.1f} | {b['bad1']:.2f} | {b['bad3']:.2f} | {b['epe']:.3f} | "
                 f"{b['d1']:.2f} |")
    return "\n".join(lines)


def _floats(text: str) -> tuple[float, ...]:
    return tuple(float(v) for v in text.split(",") if v.strip())


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", choices=DATASETS, default="kitti15")
    parser.add_argument("--root", type=Path, default=Path("../shared/data/kitti15"), help="dataset folder")
    parser.add_argument("--split", default="training")
    parser.add_argument("--out", type=Path, default=Path("out/kappa_sweep"))
    parser.add_argument("--limit", type=int, default=None, help="first N frames only")
    parser.add_argument("--k", type=int, default=LabelerConfig.k)
    parser.add_argument("--max-disp", type=int, default=None, help="default: LabelerConfig (sample: 64)")
    parser.add_argument("--kappa1", type=_floats, default=DEFAULT_KAPPA1, help="comma-separated px values")
    parser.add_argument("--kappa2", type=_floats, default=DEFAULT_KAPPA2, help="comma-separated values")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    max_disp = args.max_disp or (64 if args.dataset == "sample" else LabelerConfig.max_disp)
    cfg = LabelerConfig(k=args.k, max_disp=max_disp).validate()
    root = None if args.dataset == "sample" else args.root
    result = sweep(args.dataset, root, cfg, args.kappa1, args.kappa2, args.limit, args.split)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "sweep.json").write_text(json.dumps(result, indent=2, default=float))
    text = markdown(result)
    (args.out / "sweep.md").write_text(f"# PVM kappa sweep on {args.dataset}\n\n{text}\n")
    png = plot(result, args.out / "kappa_tradeoff.png")
    print(text)
    print(f"wrote {args.out / 'sweep.json'}, {args.out / 'sweep.md'} and {png}")


if __name__ == "__main__":
    main()
