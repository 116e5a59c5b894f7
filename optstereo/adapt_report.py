"""``optstereo-adapt``'s words: the decision's changes and the report's scores, each with the digits it needs, and
the report as Markdown."""

from __future__ import annotations

import math
from typing import Any

from optstereo.validation import SCORE_DIGITS
from pvm_labeler.common.errors import counted

#: Significant digits of a photometric error (a mean per-pixel cost, ~0.02 on a KITTI pair).
PHOTOMETRIC_FIGURES = 4
#: The most decimals a number is printed with.
MAX_DECIMALS = 8
#: The report's score keys and the :data:`optstereo.validation.SCORE_DIGITS` score each is.
REPORT_SCORES = {"held_bad3": "pvm_bad3", "held_epe": "pvm_epe", "photometric_holes": "photometric",
                 "gt_bad3": "pvm_bad3", "gt_epe": "pvm_epe"}


def decimals_for(value: float, figures: int) -> int:
    """Decimals that show ``figures`` significant digits of ``value`` (0 for 0 or a non-finite one)."""
    if not math.isfinite(value) or value == 0:
        return 0
    return max(0, figures - 1 - math.floor(math.log10(abs(value))))


def score_text(key: str, value: float) -> str:
    """A score (a :data:`~optstereo.validation.SCORE_DIGITS` key) at its decimals; a photometric error at
    :data:`PHOTOMETRIC_FIGURES` significant digits."""
    if not math.isfinite(value):
        return str(value)
    digits = SCORE_DIGITS.get(key, 3)
    if key == "photometric":
        digits = max(digits, decimals_for(value, PHOTOMETRIC_FIGURES))
    return f"{value:.{min(digits, MAX_DECIMALS)}f}"


def change_text(key: str, mean: float, margin: float) -> str:
    """'KEY CHANGE (noise MARGIN)': the mean change at the score's decimals, or more, so that the noise shows two
    significant digits (a change smaller than its score's last decimal is still readable); a change that rounds to
    zero unsigned, no change at all 'unchanged'."""
    if not (math.isfinite(mean) and math.isfinite(margin)):
        return f"{key} {mean:+} (noise {margin})"
    if mean == 0 and margin == 0:
        return f"{key} unchanged"
    digits = max(SCORE_DIGITS.get(key, 3), decimals_for(margin if margin else mean, 2))
    digits = min(digits, MAX_DECIMALS)
    change = f"{mean:+.{digits}f}"
    if float(change) == 0:
        change = f"{0:.{digits}f}"  # not "-0.000"
    return f"{key} {change} (noise {margin:.{digits}f})"


def changes_text(changes: dict[str, tuple[float, float]]) -> str:
    """The decision's changes, one :func:`change_text` per score."""
    return ", ".join(change_text(key, mean, margin) for key, (mean, margin) in changes.items())


def _teacher_words(config: dict[str, Any]) -> str:
    """The report's words for the run's targets."""
    if not config.get("teacher"):
        return "."
    if config.get("teacher_only"):
        return f"; the teacher `{config['teacher']}`'s consistent views alone (no PVM labels, no L_R / L_S)."
    return f"; the teacher `{config['teacher']}` in PVM's holes."


def _budget_words(budget: dict[str, Any] | None, minutes: float) -> str:
    """" (as many as fit 10 minutes)", or, when the timing steps alone took longer, what they took."""
    words = f"{minutes:g} minute{'' if minutes == 1 else 's'}"
    if budget and budget["steps"] * budget["s_per_step"] > minutes * 60.0:
        return f" (the timing steps alone: {budget['steps'] * budget['s_per_step'] / 60:.1f} minutes, over {words})"
    return f" (as many as fit {words})"


def report_markdown(report: dict[str, Any]) -> str:
    """The report as a short Markdown table."""
    rows = [("held-back frames: PVM bad-3 (%)", "held_bad3"), ("held-back frames: PVM EPE (px)", "held_epe"),
            ("held-back frames: photometric error in PVM's holes", "photometric_holes"),
            ("GT bad-3 (%), every frame, score only", "gt_bad3"), ("GT EPE (px), score only", "gt_epe")]
    steps = report.get("steps", report["config"]["steps"])
    minutes = report["config"].get("minutes")
    lines = ["# optstereo-adapt report", "",
             f"{counted(report['pairs'], 'pair')} ({len(report['held_back_frames'])} held back); "
             f"start `{report['init']}`; " + (counted(steps, "step") if isinstance(steps, int) else f"{steps} steps")
             + ("" if report["config"].get("steps") is not None else _budget_words(report.get("budget"), minutes))
             + (f" at lr {report['lr']:g}" if "lr" in report else "")
             + _teacher_words(report["config"]), "", "| | before | after |",
             "| --- | --- | --- |"]
    for name, key in rows:
        if key in report["before"] and not math.isnan(float(report["before"][key])):
            lines.append(f"| {name} | {score_text(REPORT_SCORES[key], float(report['before'][key]))} | "
                         f"{score_text(REPORT_SCORES[key], float(report['after'][key]))} |")
    lines += ["", f"**{report['decision']}**", "", f"checkpoint `{report['checkpoint']}`", ""]
    if not report.get("adapted", True) and report.get("trained"):
        lines += [f"the trained weights, not chosen (use them at your own risk): `{report['trained']}`", ""]
    return "\n".join(lines)
