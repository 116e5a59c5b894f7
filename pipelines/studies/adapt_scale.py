"""A5 (issue 50, docs/registrations.md): `optstereo-adapt` on the Middlebury rig with the start run at the teacher's
input scale (1.625), teacher-only targets, each training frame at the start's own scale.

    python -m pipelines.studies.adapt_scale --out /work/a5 [--scale 1.625] [--minutes 10]

Writes OUT/start.safetensors (version 15's weights, ``inference.scale`` = SCALE, the adaptive pass kept), runs the
adaptation into OUT/run (resumable: the command again continues it) and copies its report to
results/adapt/v15_middlebury_teacher_only_10min_scale<SCALE>.json. GT is read by the adaptation's report only, after
its (here impossible: 3 frames) decision.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from optstereo import adapt
from optstereo.api import load_model
from optstereo.checkpoint import export_safetensors, model_inference

RESULTS = Path("results/adapt")


def start_file(out: Path, scale: float) -> Path:
    """Version 15's weights with its inference settings but ``scale`` (float32: no int8 clips beside it)."""
    path = out / "start.safetensors"
    if not path.exists():
        model = load_model("pretrained")
        export_safetensors(path, model, inference=model_inference(model).replace(scale=scale))
    return path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--scale", type=float, default=1.625)
    parser.add_argument("--minutes", type=float, default=adapt.DEFAULT_MINUTES)
    parser.add_argument("--shared", type=Path, default=Path("../shared/data"))
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    cfg = adapt.AdaptConfig(dataset="middlebury", root=args.shared, out=args.out / "run",
                            init=start_file(args.out, args.scale), minutes=args.minutes, device="cpu",
                            teacher="pretrained-accurate", teacher_only=True, inference_scale=True)
    report = adapt.run(cfg)
    RESULTS.mkdir(parents=True, exist_ok=True)
    name = f"v15_middlebury_teacher_only_{args.minutes:g}min_scale{args.scale:g}.json"
    shutil.copyfile(args.out / "run" / "report.json", RESULTS / name)
    print(json.dumps({k: report[k] for k in ("steps", "before", "after", "decision")}, indent=1, default=str))


if __name__ == "__main__":
    main()
