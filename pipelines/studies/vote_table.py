"""What each PVM stage removes, and how good what it removes was: the vote table of docs/pvm.md.

The stages and their order are :mod:`pvm_labeler.stages`; this pools them over a dataset's GT frames (the evaluator's
GT rule: noc where present). ``--set`` overrides a LabelerConfig field; ``--recipe paper`` starts from the paper's
recipe.

    .venv/bin/python -m pipelines.studies.vote_table --root ../shared/data/kitti15 --out results/vote_table
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from pipelines.baselines import load_frames, scale_stack
from pvm_labeler.config import LabelerConfig, recipe_values
from pvm_labeler.multiscale import label_from_scales
from pvm_labeler.stages import add_counts, count_stages, stage_markdown, stage_rows


def table(frames: list, cfg: LabelerConfig, cache_dir: Path | None) -> dict[str, Any]:
    """Pooled share (% of GT-valid pixels) and bad-3 (%) of every group of ``pvm_labeler.stages`` over ``frames``."""
    counts: dict[str, list[int]] = {}
    for frame in frames:
        candidate, codes = label_from_scales(scale_stack(frame, cfg, cache_dir), cfg, with_stages=True).stages
        counts = add_counts(counts, count_stages(candidate, codes, frame.gt))
    return {"config": cfg.to_dict(), "frames": [f.frame_id for f in frames],
            "gt_valid_pixels": sum(n for n, _ in counts.values()), "rows": stage_rows(counts)}


def markdown(result: dict[str, Any]) -> str:
    """The table as Markdown, with the settings it was measured at."""
    cfg = result["config"]
    head = (f"kappa1 = {cfg['kappa1']}, kappa2 = {cfg['kappa2']}, c2_scale = {cfg['c2_scale']}, min_confidence = "
            f"{cfg['min_confidence']}, min_texture = {cfg['min_texture']}, K = {cfg['k']}, label_mode = "
            f"{cfg['label_mode']}; {len(result['frames'])} frames, {result['gt_valid_pixels']} GT-valid pixels "
            "(left view)\n\n")
    return head + stage_markdown(result["rows"])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", default="kitti15")
    parser.add_argument("--root", type=Path, default=Path("../shared/data/kitti15"))
    parser.add_argument("--out", type=Path, default=Path("results/vote_table"))
    parser.add_argument("--cache", type=Path, default=None, help="cache dir of the per-scale SGM outputs")
    parser.add_argument("--recipe", default="default", help="starting point (pvm_labeler.config.RECIPES)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a LabelerConfig field (JSON value), e.g. --set kappa2=0.1")
    args = parser.parse_args(argv)
    overrides = {k: json.loads(v) for k, _, v in (s.partition("=") for s in args.set)}
    cfg = LabelerConfig.from_dict({**recipe_values(args.recipe), **overrides})
    result = table(load_frames(args.dataset, args.root), cfg, args.cache)
    args.out.mkdir(parents=True, exist_ok=True)
    tag = "_".join([args.recipe, *(f"{k}{v}" for k, v in overrides.items())])
    (args.out / f"{tag}.json").write_text(json.dumps(result, indent=1))
    (args.out / f"{tag}.md").write_text(markdown(result))
    print(markdown(result))


if __name__ == "__main__":
    main()
