"""What each PVM stage removes, and how good what it removes was (the vote table of docs/pvm.md).

Every left-view pixel gets one code: the first stage, in the labeler's order, that removed it, or "kept". Its
candidate label is what the vote gives it with no rejection (kappas = inf, the configured ``label_mode``), so a
removed group's bad-3 says how good the labels it took away would have been. A stage earns its place when what it
removes is much worse than what it keeps.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

#: Stage codes, in the labeler's order (code = index).
GROUPS: tuple[str, ...] = ("no candidate", "C1 only", "C2 only", "C1 and C2", "confidence", "texture", "LR check",
                           "kept")


def stage_codes(
    candidate: np.ndarray, c1: np.ndarray, c2: np.ndarray, confidence: np.ndarray, texture: np.ndarray,
    label: np.ndarray, kappa1: float, kappa2: float, min_confidence: float, min_texture: int,
) -> npt.NDArray[np.uint8]:
    """(H, W) uint8 code into :data:`GROUPS` of every left-view pixel.

    Args:
        candidate: (H, W) float32 vote with no rejection (NaN where some scale is invalid).
        c1, c2: (H, W) float32 C1, C2.
        confidence: (H, W) float32 soft confidence of the vote (before the confidence filter).
        texture: (H, W) grey-level range over the census window.
        label: (H, W) float32 final label (NaN = none).
    """
    with np.errstate(invalid="ignore"):
        v1, v2 = c1 >= kappa1, c2 >= kappa2
    has = np.isfinite(candidate)
    passed = has & ~v1 & ~v2
    by_conf = passed & (confidence < min_confidence) if min_confidence > 0 else np.zeros_like(passed)
    by_texture = passed & ~by_conf & (texture < min_texture) if min_texture > 0 else np.zeros_like(passed)
    kept = np.isfinite(label)
    codes = np.zeros(candidate.shape, np.uint8)  # "no candidate"
    for code, mask in enumerate((has & v1 & ~v2, has & v2 & ~v1, has & v1 & v2, by_conf, by_texture,
                                 passed & ~by_conf & ~by_texture & ~kept, kept), start=1):
        codes[mask] = code
    return codes


def count_stages(candidate: np.ndarray, codes: np.ndarray, gt: np.ndarray) -> dict[str, list[int]]:
    """{group: [GT-valid pixels, of them with |candidate - GT| > 3]} of one frame (GT NaN = unknown)."""
    valid = np.isfinite(gt)
    with np.errstate(invalid="ignore"):
        bad = valid & (np.abs(candidate - gt) > 3)
    n = np.bincount(codes[valid], minlength=len(GROUPS))
    b = np.bincount(codes[bad], minlength=len(GROUPS))
    return {g: [int(n[i]), int(b[i])] for i, g in enumerate(GROUPS)}


def add_counts(total: dict[str, list[int]], counts: dict[str, list[int]]) -> dict[str, list[int]]:
    """Pool two count dicts (pixels pooled over frames)."""
    return {g: [a + b for a, b in zip(total.get(g, [0, 0]), counts.get(g, [0, 0]), strict=True)] for g in GROUPS}


def stage_rows(counts: dict[str, list[int]]) -> dict[str, dict[str, Any]]:
    """{group: {"share": % of GT-valid pixels, "bad3": % of the group's candidates (None if empty)}}."""
    n_valid = sum(n for n, _ in counts.values())
    rows = {g: {"share": 100.0 * n / n_valid if n_valid else 0.0, "bad3": 100.0 * b / n if n else None}
            for g, (n, b) in ((g, counts.get(g, [0, 0])) for g in GROUPS)}
    rows["no candidate"]["bad3"] = None  # no disparity at any scale: nothing to be right or wrong
    return rows


def stage_markdown(rows: dict[str, dict[str, Any]]) -> str:
    """The vote table as Markdown."""
    lines = ["| removed by | share of GT-valid pixels (%) | bad-3 of their candidate labels (%) |", "|---|---:|---:|"]
    for group, row in rows.items():
        bad3 = "n/a" if row["bad3"] is None else f"{row['bad3']:.2f}"
        lines.append(f"| {group} | {row['share']:.2f} | {bad3} |")
    return "\n".join(lines) + "\n"
