"""The README's Python API snippet runs as written (with the shipped weights) and gives a sensible disparity map."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"


def api_snippet() -> str:
    """The first ```python block after the '## Python API' heading."""
    text = README.read_text()
    section = text[text.index("## Python API"):]
    match = re.search(r"```python\n(.*?)```", section, re.S)
    assert match, "README: no python block under '## Python API'"
    return match.group(1)


def test_readme_api_snippet_runs() -> None:
    namespace: dict = {}
    exec(compile(api_snippet(), str(README), "exec"), namespace)  # noqa: S102 (our own README)
    disp, left = namespace["disp"], namespace["left"]
    assert disp.shape == left.shape[:2] and disp.dtype == np.float32
    gt = namespace["gt"]
    valid = np.isfinite(gt)
    # the shipped model (KITTI-trained) on Middlebury's motorcycle: most pixels within 3 px of GT
    assert np.mean(np.abs(disp[valid] - gt[valid]) <= 3.0) > 0.75  # measured 0.83 (bad-3 17 %)
