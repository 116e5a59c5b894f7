"""PVM-HITNet vs PVM-OptStereo (and the loss variants), trained on the same labels for the same CPU budget.

The runs (commands in ``out/cmp/commands.txt`` and in RESULTS.md) train from scratch on the PVM labels of
``../shared/data/kitti_unlabelled`` only, concurrently in pairs with one torch thread each, so both arms of a pair
see the same machine load. This script evaluates each run's last checkpoint by one ruler on the GT frames of
``../shared/data`` (dense prediction, every GT-valid pixel, pooled; ``optstereo.evaluate``) and times a KITTI-size
frame, then writes ``results/compare/<name>.json`` and ``results/compare/report.md``.

    .venv/bin/python -m pipelines.studies.compare_networks out/cmp/hitnet out/cmp/optstereo_l1 ...
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pipelines.studies.train_pretrained import EVAL_SETS, SHARED, _machine

RESULTS = Path("results/compare")
SETS = ("kitti15", "kitti12", "middlebury")


def frame_ms(model: torch.nn.Module, repeats: int = 3) -> float:
    """Median ms of one test-mode forward at KITTI size (376x1248, the padded 375x1242), 2 threads."""
    from optstereo.inference.engine import infer
    from pipelines.bench_export import _medians

    rng = np.random.default_rng(0)
    left = rng.integers(0, 255, (375, 1242, 3), dtype=np.uint8)
    right = np.roll(left, -4, axis=1)
    return 1000.0 * _medians({"infer": lambda: infer(model, left, right)}, repeats)["infer"]


def evaluate_run(run_dir: Path) -> dict[str, Any]:
    """Metrics of RUN_DIR's last checkpoint on every GT set, its training summary and its KITTI-size time."""
    from optstereo.api import load_model
    from optstereo.evaluate import evaluate_model

    torch.set_num_threads(2)
    model = load_model(run_dir)
    out: dict[str, Any] = {"run": str(run_dir), **_machine()}
    summary = Path(run_dir) / "summary.json"
    if summary.exists():
        out["train_summary"] = json.loads(summary.read_text())
    out["params"] = sum(p.numel() for p in model.parameters())
    for name, reader, root, _ in EVAL_SETS:
        if name in SETS:
            result = evaluate_model(model, reader, SHARED / root, save_maps=False,
                                    out_dir=Path("out/cmp/eval") / Path(run_dir).name / name)
            out[name] = result.summary
    out["ms_per_kitti_frame"] = frame_ms(model)
    return out


def report(docs: dict[str, dict[str, Any]]) -> str:
    """One Markdown row per run."""
    lines = ["| run | params | steps | KITTI 2015 bad-3 % | D1-all % | AEPE px | KITTI 2012 bad-3 % "
             "| Middlebury bad-3 % | ms per KITTI frame (2 threads) |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, d in docs.items():
        k15 = d["kitti15"]
        steps = d.get("train_summary", {}).get("step", "?")
        lines.append(f"| `{name}` | {d['params'] / 1e6:.2f} M | {steps} | {k15['bad3']:.2f} | {k15['d1_all']:.2f} | "
                     f"{k15['epe']:.3f} | {d['kitti12']['bad3']:.2f} | {d['middlebury']['bad3']:.2f} | "
                     f"{d['ms_per_kitti_frame']:.0f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="run directories (their last checkpoint is evaluated)")
    args = parser.parse_args(argv)
    RESULTS.mkdir(parents=True, exist_ok=True)
    for run in args.runs:
        doc = evaluate_run(run)
        (RESULTS / f"{run.name}.json").write_text(json.dumps(doc, indent=1, default=float))
        print(run.name, {k: round(doc[k]["bad3"], 2) for k in SETS}, round(doc["ms_per_kitti_frame"]), flush=True)
    docs = {p.stem: json.loads(p.read_text()) for p in sorted(RESULTS.glob("*.json"))}
    (RESULTS / "report.md").write_text(report(docs))
    print(report(docs))


if __name__ == "__main__":
    main()
