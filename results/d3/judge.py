"""D3's rule (docs/registrations.md), as pipelines.studies.judge_distill runs it (this script's earlier body gave
the same verdict). Usage: python judge.py (then, only for a candidate: python judge.py gt)"""
import sys

from pipelines.studies.judge_distill import main

main(["/work/t14/d3/run", "--valset", "/work/valset", "--out", "/work/t14/d3/judge", "--pick",
      "lowest-teacher",
      *(["--gt"] if sys.argv[1:] == ["gt"] else [])])
