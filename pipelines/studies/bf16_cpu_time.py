"""One-off check (issue 52): the default in float32 (the engineered pass) against bf16 autocast (the plain forward:
the engineered pass is float32-only) on a CPU with native bf16, each beside OpenCV SGBM-HH on 4 KITTI 2015 frames,
2 threads, median of the per-frame ratios.

    python -m pipelines.studies.bf16_cpu_time [--shared ../shared/data]
"""

from __future__ import annotations

import argparse
import functools
from pathlib import Path

import cv2
import torch

from optstereo.api import load_model
from optstereo.inference.engine import cpu_has_native_bf16, infer
from pipelines.bench_labeler import _opencv
from pipelines.bench_models import THREADS, _frames, beside_sgbm


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("--shared", type=Path, default=Path("../shared/data"))
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    if not cpu_has_native_bf16():
        raise SystemExit("this CPU has no native bf16 (AVX512-BF16 / AMX): nothing to measure")
    torch.set_num_threads(THREADS)
    model, frames, sgbm = load_model("pretrained"), _frames(args.shared), _opencv(cv2.STEREO_SGBM_MODE_HH)
    print("float32:", beside_sgbm(model, frames, args.repeats, sgbm))
    print("bf16:", beside_sgbm(model, frames, args.repeats, sgbm, run=functools.partial(infer, amp="bf16")))


if __name__ == "__main__":
    main()
