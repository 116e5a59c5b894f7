"""`make bench`: run every benchmark section in one process and write bench/report.{json,md}.

Each section is a module ``pipelines.bench_<name>`` exposing ``run(shared: Path) -> dict`` that
returns ``{"title": str, "results": <JSON-able>, "markdown": str}``. Sections time against a
baseline measured in the same run (OpenCV StereoSGBM, naive references), so ratios are meaningful
on a noisy shared machine. Select sections with ``--only labeler,network``: the sections not run keep
their last results from the existing report, each section stamped with its own commit, date and CPU.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import os
import platform
import time
from pathlib import Path

from pvm_labeler.common.version import cpuinfo_flags, git_commit

SECTIONS = ("models", "labeler", "job", "network", "train", "export")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--shared", type=Path, default=Path("../shared/data"), help="real data root")
    parser.add_argument("--out", type=Path, default=Path("bench"), help="report folder")
    parser.add_argument("--only", default=",".join(SECTIONS), help="comma-separated sections")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    args.out.mkdir(parents=True, exist_ok=True)
    meta = {"commit": git_commit(), "machine": platform.platform(), "cpu": cpu_summary(),
            "date": time.strftime("%Y-%m-%d %H:%M:%S")}
    report = _load_report(args.out / "report.json")
    for name in [s.strip() for s in args.only.split(",") if s.strip()]:
        try:
            module = importlib.import_module(f"pipelines.bench_{name}")
        except ModuleNotFoundError as exc:
            logging.warning("bench section %s not available: %s", name, exc)
            continue
        logging.info("running bench section %s", name)
        section = module.run(args.shared)
        report["sections"][name] = section["results"]
        report["section_meta"][name] = {**meta, "title": section["title"], "markdown": section["markdown"]}
        # Write after every section so a long run leaves partial results behind.
        (args.out / "report.json").write_text(json.dumps(report, indent=2, default=float))
        (args.out / "report.md").write_text(render(report))
    print(f"wrote {args.out / 'report.json'} and {args.out / 'report.md'}")


def cpu_summary() -> str:
    """CPU model, core count and the SIMD extensions that decide our kernels' speed (AVX2 / AVX-512 / bf16)."""
    model = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name":
                model = value.strip()
                break
    except OSError:
        pass
    flags = cpuinfo_flags() or set()
    simd = [f for f in ("avx2", "avx512f", "avx512bw", "avx512_bf16", "amx_bf16") if f in flags]
    return f"{model}, {os.cpu_count()} cores, {' '.join(simd) or 'no AVX2'}"


def _load_report(path: Path) -> dict:
    """The existing report (sections not re-run keep their results), or an empty one."""
    empty: dict = {"sections": {}, "section_meta": {}}
    if not path.exists():
        return empty
    try:
        old = json.loads(path.read_text())
    except json.JSONDecodeError:
        logging.warning("%s is not valid JSON; starting a new report", path)
        return empty
    if "section_meta" not in old:  # a report from before per-section stamps: its markdown is not kept, rerun it
        return empty
    return {"sections": old["sections"], "section_meta": old["section_meta"]}


def render(report: dict) -> str:
    """Markdown of all sections in SECTIONS order, each under a line saying when, where and at which commit."""
    md = ["# Benchmark report\n", "Each section says the commit, date and CPU of the run that measured it "
          "(`make bench` re-runs all; `--only NAME` re-runs one and keeps the others).\n"]
    order = [n for n in SECTIONS if n in report["section_meta"]]
    order += [n for n in report["section_meta"] if n not in order]
    for name in order:
        m = report["section_meta"][name]
        md.append(f"## {m['title']}\n\n_measured at commit `{m['commit']}`, {m['date']}, {m['cpu']}_\n\n"
                  f"{m['markdown']}\n")
    return "\n".join(md)


if __name__ == "__main__":
    main()
