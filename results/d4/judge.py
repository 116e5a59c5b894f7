"""D4's rule (docs/registrations.md), as pipelines.studies.judge_distill runs it (this script's earlier body gave
the same verdict). Usage: python judge.py (then, only for a candidate: python judge.py gt)"""
import sys

from pipelines.studies.judge_distill import main

main(["/work/t15/d4/run", "--valset", "/work/valset", "--out", "/work/t15/d4/judge", "--pick",
      "last",
      *(["--gt"] if sys.argv[1:] == ["gt"] else [])])
