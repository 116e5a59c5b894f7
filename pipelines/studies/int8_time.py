"""Q1's time eligibility (issue 52, docs/registrations.md): the default's int8 encoder against its float32 one,
beside OpenCV SGBM-HH on `make bench`'s four KITTI frames, three times under the AVX2 proxy and once uncapped.

    python -m pipelines.studies.int8_time --out results/int8/time.json
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
from pathlib import Path

import cv2
import torch

from optstereo.api import load_model
from pipelines import bench_models


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--shared", type=Path, default=Path("../shared/data"))
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    proxy = [bench_models.proxy_row(args.shared, "pretrained") for _ in range(args.runs)]
    torch.set_num_threads(bench_models.THREADS)
    model, frames = load_model("pretrained"), bench_models._frames(args.shared)
    sgbm = bench_models._opencv(cv2.STEREO_SGBM_MODE_HH)
    uncapped = {"int8": bench_models.beside_sgbm(model, frames, bench_models.REPEATS, sgbm),
                "float32": bench_models.beside_sgbm(model, frames, bench_models.REPEATS, sgbm,
                                                    run=bench_models.float32_infer),
                "torch_capability": torch.backends.cpu.get_cpu_capability()}
    median = statistics.median(p["ratio"] for p in proxy)
    verdict = {"proxy_median_ratio": median, "proxy_le_2": median <= 2.0,
               "uncapped_int8_faster": uncapped["int8"]["s_per_frame"] < uncapped["float32"]["s_per_frame"]}
    result = {"cpu": platform.processor() or platform.machine(), "proxy_runs": proxy, "uncapped": uncapped,
              "verdict": verdict}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    for p in proxy:
        print(f"proxy: int8 {p['ratio']:.2f}x, float32 {p['float32_ratio']:.2f}x SGBM-HH")
    print(f"uncapped ({uncapped['torch_capability']}): int8 {uncapped['int8']['ratio']:.2f}x, "
          f"float32 {uncapped['float32']['ratio']:.2f}x; verdict {verdict}")


if __name__ == "__main__":
    main()
