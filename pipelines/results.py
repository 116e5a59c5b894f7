"""`make results`: study 1 of RESULTS.md (the PVM ablation: K x kappa trade-off against SGM baselines), end to end.

For every frame with GT in ../shared/data (15 KITTI 2015 frames, KITTI 2012, the Middlebury 2001/2003/MiddEval3
scenes, FlyingThings3D) the 8-scale pyramid is matched ONCE (``multiscale.compute_scales`` with K = 8); the stacks
for K = 1, 2, 4, 6 are its first K scales, which are exactly what the labeler computes for that K (eps is drawn
sequentially from the per-frame generator, so the first K draws do not depend on K: asserted below). Then, pooled
over pixels per dataset:

* the paper's vote (min_confidence = 0): every (kappa1, kappa2) of a grid, voting + LRDCC, and its Pareto front
  (lowest bad-3 at each density) per K. K = 1 has no spread across scales, so it is one point: plain SGM + LRDCC.
* the labeler's default recipe (kappas of ``LabelerConfig``, confidence filter swept over ``min_confidence``) per K.
* baselines on the same matcher: full-resolution SGM + LRDCC, and SGM + LRDCC + a uniqueness-ratio filter swept
  over its threshold (``pipelines.baselines``).
* bad-3 of each curve interpolated at matched densities 30 / 50 / 70 %.

Writes ``results/pvm_ablation.{json,md}``, ``results/pvm_ablation_<dataset>.png`` and rebuilds the generated blocks
of ``RESULTS.md`` from that and ``results/training.md`` (studies 2-3, written by
``python -m pipelines.studies.train_studies
report``); the sections written by hand around them are kept.

Usage: ``.venv/bin/python -m pipelines.results --shared ../shared/data --out results`` (about 5 min on 2 cores).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pipelines.baselines import MATCHED_DENSITIES, CurvePoint, bad3_at_density, evaluate, score_curve
from pvm_labeler.common.atomic import atomic_path
from pvm_labeler.common.datasets import discover, load_pair
from pvm_labeler.common.errors import InputError
from pvm_labeler.config import LabelerConfig
from pvm_labeler.multiscale import ScaleStack, compute_scales, draw_eps, label_from_scales, lr_check

logger = logging.getLogger("pipelines.results")

KS = (1, 2, 4, 6, 8)
KAPPA1 = (0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 5.0)
KAPPA2 = (0.02, 0.05, 0.1, 0.2, 0.4, 0.6, 1.0)
# up to 0.9 so that every curve reaches the low matched densities (c of good KITTI matches is ~0.6-0.9)
MIN_CONFIDENCE = tuple(float(v) for v in np.round(np.linspace(0.0, 0.9, 19), 3))
#: (group, dataset reader, folder under --shared, search range; None = the reader's hint, e.g. MiddEval3 ndisp)
SOURCES = (
    ("kitti15", "kitti15", "kitti15", 192),
    ("kitti12", "kitti12", "kitti12", 192),
    ("middlebury", "middlebury", "middlebury2001", 32),  # tsukuba: GT <= 15 px
    ("middlebury", "middlebury", "middlebury2003", 64),  # cones (quarter size): GT <= 55 px
    ("middlebury", "middlebury", "middlebury_eval3", None),  # Motorcycle Q: calib ndisp
    ("sceneflow", "sceneflow", "sceneflow", 192),
)


def sub_stack(stack: ScaleStack, k: int) -> ScaleStack:
    """The first k scales of a stack (what the labeler computes with K = k for the same frame and seed)."""
    return dataclasses.replace(stack, disp_l=stack.disp_l[:k], conf_l=stack.conf_l[:k], disp_r=stack.disp_r[:k],
                               conf_r=stack.conf_r[:k], eps=stack.eps[:k], factors=stack.factors[:k])


@dataclasses.dataclass
class Frame:
    """One frame's 8-scale stack, the config it was matched with, and its GT (noc where the dataset has it)."""

    group: str
    frame_id: str
    cfg: LabelerConfig
    stack: ScaleStack
    gt: np.ndarray


def load_frames(shared: Path) -> list[Frame]:
    """Match every GT frame of ``shared`` once with K = max(KS)."""
    frames = []
    for group, reader, folder, max_disp in SOURCES:
        root = shared / folder
        if not root.is_dir():
            logger.warning("%s missing: group %s skipped", root, group)
            continue
        for ref in discover(reader, root):
            sample = load_pair(ref)
            gt = sample.gt_noc if sample.gt_noc is not None else sample.gt
            if gt is None:
                continue
            cfg = LabelerConfig(k=max(KS), max_disp=int(max_disp or sample.max_disp or 192)).validate()
            t0 = time.perf_counter()
            try:
                stack = compute_scales(sample.left, sample.right, cfg, ref.frame_id, uniqueness=True)
            except InputError as exc:  # e.g. too small for K = 8 at this search range
                logger.warning("%s/%s skipped: %s", group, ref.frame_id, exc)
                continue
            for k in KS:  # the sub-stack is the K-scale labeler's pyramid
                assert np.array_equal(draw_eps(cfg.seed, ref.frame_id, k), stack.eps[:k])
            frames.append(Frame(group, ref.frame_id, cfg, stack, gt))
            logger.info("%s/%s matched at %d scales in %.1f s", group, ref.frame_id, max(KS),
                        time.perf_counter() - t0)
    return frames


def _point(metrics: dict[str, float], **params: float) -> dict[str, float]:
    return {**params, **{k: metrics[k] for k in ("density", "bad1", "bad3", "epe", "d1")}}


def pareto(points: Sequence[dict[str, float]]) -> list[dict[str, float]]:
    """Points not beaten by another with higher-or-equal density AND lower-or-equal bad-3 (sorted by density)."""
    finite = [p for p in points if np.isfinite(p["bad3"]) and p["density"] > 0]
    front = [p for p in finite if not any(q is not p and q["density"] >= p["density"] and q["bad3"] <= p["bad3"]
                                          and (q["density"], q["bad3"]) != (p["density"], p["bad3"]) for q in finite)]
    return sorted(front, key=lambda p: p["density"])


def _matched(points: Sequence[dict[str, float]]) -> dict[str, float]:
    curve = [CurvePoint(0.0, p["density"], p["bad3"], p["epe"]) for p in points]
    return {f"{d:g}": bad3_at_density(curve, d) for d in MATCHED_DENSITIES}


def study_group(frames: Sequence[Frame]) -> dict[str, Any]:
    """All curves of one dataset group (pooled over its frames' pixels)."""
    gts = [f.gt for f in frames]
    out: dict[str, Any] = {"frames": [f.frame_id for f in frames], "vote": {}, "default": {}}
    for k in KS:
        stacks = [sub_stack(f.stack, k) for f in frames]
        grid = [(k1, k2) for k1 in KAPPA1 for k2 in KAPPA2] if k > 1 else [(KAPPA1[0], KAPPA2[0])]
        pts = []
        for k1, k2 in grid:
            labels = [label_from_scales(st, dataclasses.replace(f.cfg, k=k, kappa1=k1, kappa2=k2, min_confidence=0.0))
                      .label for st, f in zip(stacks, frames, strict=True)]
            pts.append(_point(evaluate(labels, gts), kappa1=k1, kappa2=k2))
        sweep = []
        for t in MIN_CONFIDENCE:
            labels = [label_from_scales(st, dataclasses.replace(f.cfg, k=k, min_confidence=t)).label
                      for st, f in zip(stacks, frames, strict=True)]
            sweep.append(_point(evaluate(labels, gts), min_confidence=t))
        front = pareto(pts)
        out["vote"][str(k)] = {"grid": pts, "front": front, "matched": _matched(front)}
        out["default"][str(k)] = {"sweep": sweep, "matched": _matched(sweep),
                                  "at_default": next(p for p in sweep if p["min_confidence"] == 0.15)}
        logger.info("K=%d done", k)
    sgm_lr = [lr_check(f.stack.full_res["disp_l"], f.stack.full_res["disp_r"], f.cfg.lr_threshold)[0] for f in frames]
    uniq = [f.stack.full_res["uniqueness_l"] for f in frames]
    pooled_u = np.concatenate([u[np.isfinite(d)] for d, u in zip(sgm_lr, uniq, strict=True)])
    thresholds = np.unique(np.quantile(pooled_u[np.isfinite(pooled_u)], np.linspace(0.0, 0.98, 50)))
    ucurve = [dict(threshold=p.threshold, density=p.density, bad3=p.bad3, epe=p.epe)
              for p in score_curve(sgm_lr, uniq, gts, thresholds)]
    out["sgm_lr"] = _point(evaluate(sgm_lr, gts))
    out["sgm_raw"] = _point(evaluate([f.stack.full_res["disp_l"] for f in frames], gts))
    out["uniq"] = {"curve": ucurve, "matched": _matched(ucurve)}
    return out


def plot_group(name: str, res: dict[str, Any], path: Path) -> Path:
    """2 x 2 panels: density vs bad-3 / AEPE; top the paper's vote (Pareto fronts), bottom the default recipe."""
    import matplotlib  # lazy: matplotlib.use("Agg") must run before pyplot loads

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: after matplotlib.use("Agg")

    fig, axes = plt.subplots(2, 2, figsize=(12, 9))
    colours = plt.cm.viridis(np.linspace(0, 0.9, len(KS)))
    for row, mode in enumerate(("vote", "default")):
        for col, (key, ylabel) in enumerate((("bad3", "bad-3 (%)"), ("epe", "AEPE (px)"))):
            ax = axes[row, col]
            for colour, k in zip(colours, KS, strict=True):
                pts = res[mode][str(k)]["front" if mode == "vote" else "sweep"]
                if mode == "vote":
                    grid = res[mode][str(k)]["grid"]
                    ax.scatter([p["density"] for p in grid], [p[key] for p in grid], s=6, color=colour, alpha=0.3)
                ax.plot([p["density"] for p in pts], [p[key] for p in pts], "o-", ms=3, color=colour,
                        label=f"PVM K={k}" + (" (SGM + LRDCC)" if k == 1 and mode == "vote" else ""))
            u = res["uniq"]["curve"]
            ax.plot([p["density"] for p in u], [p[key] for p in u], "k--", label="SGM + LRDCC + uniqueness")
            ax.plot([res["sgm_lr"]["density"]], [res["sgm_lr"][key]], "r*", ms=12, label="SGM + LRDCC")
            ax.set_xlabel("label density (% of GT-valid pixels)")
            ax.set_ylabel(ylabel)
            ax.grid(True, alpha=0.3)
            top = max(res["sgm_lr"][key] * 1.3, 1e-3)
            ax.set_ylim(0, top)
            title = ("paper's vote: Pareto front over the kappa grid (dots), min_confidence = 0" if mode == "vote"
                     else f"default kappas, confidence filter swept ({MIN_CONFIDENCE[0]} ... {MIN_CONFIDENCE[-1]})")
            ax.set_title(title, fontsize=9)
            ax.legend(fontsize=7)
    fig.suptitle(f"PVM ablation on {name} ({len(res['frames'])} frames, pooled over pixels)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _f(v: float, nd: int = 2) -> str:
    return "n/a" if v is None or not np.isfinite(v) else f"{v:.{nd}f}"


def markdown(results: dict[str, Any], png: dict[str, str], seconds: float) -> str:
    """Study 1 of RESULTS.md."""
    d = LabelerConfig()
    lines = [
        "## Study 1: PVM ablation (K and the kappas) against SGM baselines",
        "",
        "Produced by `make results` (`.venv/bin/python -m pipelines.results --shared ../shared/data --out results`, "
        f"{seconds / 60:.1f} min on this 2-core machine). Every frame with GT in `../shared/data` is matched once "
        "at 8 scales; K < 8 uses the first K of them, which is exactly the K-scale labeler's pyramid for that frame "
        "and seed (asserted). Metrics are pooled over pixels; GT = `disp_noc` where the dataset has it. "
        "Density = labelled / GT-valid pixels. SGM is our matcher (census 5x5, 8 paths, P1 = 8, P2 = 64); "
        "'SGM + LRDCC' is full resolution, both views, 1-px LR check; the uniqueness baseline adds a "
        "1 - S_min / S_second >= t filter swept over t.",
        "",
        f"Grid: kappa1 in {list(KAPPA1)} px, kappa2 in {list(KAPPA2)}; default recipe = kappa1 {d.kappa1}, "
        f"kappa2 {d.kappa2}, label '{d.label_mode}', min_confidence swept over {MIN_CONFIDENCE[0]}-"
        f"{MIN_CONFIDENCE[-1]} (default {d.min_confidence}).",
        "",
    ]
    lines += [defaults_text(results), ""]
    for name, res in results.items():
        lines += [f"### {name} ({len(res['frames'])} frames: {', '.join(res['frames'])})", "",
                  f"![PVM ablation on {name}]({png[name]})", "",
                  "bad-3 (%) at matched density, interpolated along each curve (n/a = the curve never reaches it):",
                  "", "| method | " + " | ".join(f"@ {x:g} %" for x in MATCHED_DENSITIES) + " |",
                  "|---|" + "---:|" * len(MATCHED_DENSITIES)]
        rows = [("SGM + LRDCC + uniqueness filter", res["uniq"]["matched"])]
        rows += [(f"PVM K = {k}, paper's vote (kappa front)", res["vote"][str(k)]["matched"]) for k in KS if k > 1]
        rows += [(f"PVM K = {k}, default kappas + confidence sweep", res["default"][str(k)]["matched"]) for k in KS]
        for label, m in rows:
            lines.append(f"| {label} | " + " | ".join(_f(m[f"{x:g}"]) for x in MATCHED_DENSITIES) + " |")
        lines += ["", "Single operating points:", "", "| method | density % | bad-3 % | AEPE px | D1 % |",
                  "|---|---:|---:|---:|---:|"]
        pts = [("SGM, raw (no LR check)", res["sgm_raw"]), ("SGM + LRDCC (= PVM K = 1, no filter)", res["sgm_lr"])]
        pts += [(f"PVM K = {k}, defaults (min_confidence 0.15)", res["default"][str(k)]["at_default"]) for k in KS]
        for label, p in pts:
            lines.append(f"| {label} | {_f(p['density'], 1)} | {_f(p['bad3'])} | {_f(p['epe'], 3)} | {_f(p['d1'])} |")
        lines += ["", verdict(res), ""]
    return "\n".join(lines)


def defaults_text(results: dict[str, Any]) -> str:
    """The defaults and why, with the KITTI 2015 numbers that support (or qualify) them."""
    d = LabelerConfig()
    res = results.get("kitti15")
    if res is None:
        return ""
    cells = []
    for k in KS:
        m = res["default"][str(k)]["matched"]
        cells.append(f"K = {k}: " + " / ".join(_f(m[f"{x:g}"]) for x in MATCHED_DENSITIES))
    u = res["uniq"]["matched"]
    base = " / ".join(_f(u[f"{x:g}"]) for x in MATCHED_DENSITIES)
    at = res["default"][str(d.k)]["at_default"]
    keys = [f"{x:g}" for x in MATCHED_DENSITIES]

    def beats(k: int) -> bool:
        m = res["default"][str(k)]["matched"]
        return all(np.isfinite(m[x]) and np.isfinite(u[x]) and m[x] < u[x] for x in keys)

    multi = [k for k in KS if k > 1]
    claim_multi = ("Every K >= 2 beats the baseline at all three densities" if all(beats(k) for k in multi)
                   else "Not every K >= 2 beats the baseline at all three densities (see the table below)")
    claim_k1 = "K = 1 (the same confidence filter on a single scale) does not" if not beats(1) else "so does K = 1"
    k4, k6 = res["default"]["4"]["matched"], res["default"]["6"]["matched"]
    k4_better = sum(k4[x] <= k6[x] for x in keys if np.isfinite(k4[x]) and np.isfinite(k6[x]))
    return (
        "**Defaults and why.** The labeler ships K = {k}, kappa1 = {k1} px, kappa2 = {k2}, label = scale-weighted "
        "mean, min_confidence = {mc}. K = 6 is the paper's and the issue's choice; on the 15 KITTI 2015 frames "
        "the default recipe gives bad-3 at 30 / 50 / 70 % density of {cells} (SGM + LRDCC + uniqueness: {base}). "
        "{claim_multi}, and {claim_k1}: the multi-scale vote is what buys the quality. K = 4 has the lower or equal "
        "bad-3 at {k4_better} of the 3 densities against K = 6 (and is cheaper); with 15 frames such differences "
        "are within what another frame set could reverse, so the default stays at the paper's K = 6 and `--k 4` is "
        "a measured alternative. The paper's pure vote "
        "(min_confidence = 0, top row of the figures) needs a kappa grid search per K and is less clean at "
        "matched density than the confidence-filtered recipe, which is why the confidence filter (beyond the "
        "paper, docs/pvm.md) is on by default. At the defaults: density {dens} % of GT-valid pixels, bad-3 {b3} %, "
        "AEPE {epe} px."
    ).format(k=d.k, k1=d.kappa1, k2=d.kappa2, mc=d.min_confidence, cells="; ".join(cells), base=base,
             claim_multi=claim_multi, claim_k1=claim_k1, k4_better=k4_better,
             dens=_f(at["density"], 1), b3=_f(at["bad3"]), epe=_f(at["epe"], 3))


def verdict(res: dict[str, Any]) -> str:
    """One generated sentence per group: where the default recipe beats the uniqueness baseline, and the best K."""
    k_default = LabelerConfig().k
    ours = res["default"][str(k_default)]["matched"]
    base = res["uniq"]["matched"]
    keys = [f"{d:g}" for d in MATCHED_DENSITIES]
    both = [k for k in keys if np.isfinite(ours[k]) and np.isfinite(base[k])]
    wins = [k for k in both if ours[k] < base[k]]
    best = []
    for key in keys:
        vals = {k: res["default"][str(k)]["matched"][key] for k in KS}
        vals = {k: v for k, v in vals.items() if np.isfinite(v)}
        if vals:
            best.append(f"{key} %: K = {min(vals, key=vals.get)}")
    return (f"**Generated verdict:** with the default recipe (K = {k_default}) PVM has lower bad-3 than SGM + LRDCC + "
            f"uniqueness at {len(wins)} of the {len(both)} matched densities both curves reach "
            f"({', '.join(k + ' %' for k in wins) or 'none'}). Lowest bad-3 along the confidence sweeps: "
            f"{'; '.join(best) or 'n/a'}.")


HEADER = """# Results

Every number and figure here was printed by a command in `pipelines/` on the 2-core CPU machine this project is
developed on; the command is named next to it. Study 1 (the PVM trade-off) reruns end to end with `make results`;
studies 2 and 3 (training) are recorded with their exact commands, seeds and configs and their checkpoints can be
re-evaluated with `optstereo-eval`.

"""


#: Generated blocks of RESULTS.md, each between a begin and an end marker; everything outside them (the sections
#: written by hand about the shipped model, issue 15, ...) is kept as it is when the blocks are rebuilt.
BEGIN = "<!-- generated: {} (pipelines/results.py rebuilds it; edits inside are overwritten) -->"
END = "<!-- end generated: {} -->"


def replace_block(text: str, name: str, body: str) -> str:
    """``text`` with the block ``name`` set to ``body`` (appended at the end when the file has no such block yet)."""
    begin, end = BEGIN.format(name), END.format(name)
    block = f"{begin}\n{body.rstrip()}\n{end}\n"
    i = text.find(begin)
    if i < 0:
        return text.rstrip("\n") + "\n\n" + block
    j = text.find(end, i)
    if j < 0:
        raise ValueError(f"RESULTS.md: block {name!r} has no end marker {end!r}; fix the file by hand")
    return text[:i] + block + text[j + len(end):].removeprefix("\n")


def assemble(out: Path, study1: str) -> Path:
    """Rebuild RESULTS.md's generated blocks: study 1 and results/training.md (studies 2-3); keep the rest."""
    path = out.parent / "RESULTS.md" if out.name == "results" else out / "RESULTS.md"
    text = path.read_text() if path.is_file() else HEADER
    training = out / "training.md"
    text = replace_block(text, "study 1", study1)
    text = replace_block(text, "studies 2-3", training.read_text() if training.is_file() else
                         "## Studies 2-3\n\nNot yet produced: run "
                          "`.venv/bin/python -m pipelines.studies.train_studies all`.\n")
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shared", type=Path, default=Path("../shared/data"), help="real data root")
    parser.add_argument("--out", type=Path, default=Path("results"), help="results folder (RESULTS.md goes beside it)")
    parser.add_argument("--assemble-only", action="store_true", help="rebuild RESULTS.md from results/*.md")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    args.out.mkdir(parents=True, exist_ok=True)
    md_path = args.out / "pvm_ablation.md"
    if not args.assemble_only:
        t0 = time.perf_counter()
        frames = load_frames(args.shared)
        if not frames:
            raise SystemExit(f"no frames with GT under {args.shared}")
        results: dict[str, Any] = {}
        png: dict[str, str] = {}
        for name in dict.fromkeys(f.group for f in frames):
            res = study_group([f for f in frames if f.group == name])
            results[name] = res
            path = plot_group(name, res, args.out / f"pvm_ablation_{name}.png")
            png[name] = f"{args.out.name}/{path.name}"
        seconds = time.perf_counter() - t0
        (args.out / "pvm_ablation.json").write_text(json.dumps({"seconds": seconds, "groups": results}, indent=1,
                                                               default=float))
        md_path.write_text(markdown(results, png, seconds))
    print(f"wrote {assemble(args.out, md_path.read_text())}")


if __name__ == "__main__":
    main()
