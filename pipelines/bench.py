"""`make bench`: run every benchmark section in one process and write bench/report.{json,md}.

Each section is a module ``pipelines.bench_<name>`` exposing ``run(shared: Path) -> dict`` that
returns ``{"title": str, "results": <JSON-able>, "markdown": str}``. Sections time against a
baseline measured in the same run (OpenCV StereoSGBM, naive references), so ratios are meaningful
on a noisy shared machine. Select sections with ``--only labeler,network``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import platform
import subprocess
import time
from pathlib import Path

SECTIONS = ("labeler", "job", "network", "train")


def _git_commit() -> str:
    try:
        cmd = ["git", "rev-parse", "--short", "HEAD"]
        return subprocess.run(cmd, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--shared", type=Path, default=Path("../shared/data"), help="real data root")
    parser.add_argument("--out", type=Path, default=Path("bench"), help="report folder")
    parser.add_argument("--only", default=",".join(SECTIONS), help="comma-separated sections")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    args.out.mkdir(parents=True, exist_ok=True)
    meta = {"commit": _git_commit(), "machine": platform.platform(), "processor": platform.processor(),
            "date": time.strftime("%Y-%m-%d %H:%M:%S")}
    report: dict = {"meta": meta, "sections": {}}
    md = [f"# Benchmark report\n\ncommit `{meta['commit']}`, {meta['date']}, {meta['machine']}\n"]
    for name in [s.strip() for s in args.only.split(",") if s.strip()]:
        try:
            module = importlib.import_module(f"pipelines.bench_{name}")
        except ModuleNotFoundError as exc:
            logging.warning("bench section %s not available: %s", name, exc)
            continue
        logging.info("running bench section %s", name)
        section = module.run(args.shared)
        report["sections"][name] = section["results"]
        md.append(f"## {section['title']}\n\n{section['markdown']}\n")
        # Write after every section so a long run leaves partial results behind.
        (args.out / "report.json").write_text(json.dumps(report, indent=2, default=float))
        (args.out / "report.md").write_text("\n".join(md))
    print(f"wrote {args.out / 'report.json'} and {args.out / 'report.md'}")


if __name__ == "__main__":
    main()
