"""pipelines/studies/time_trade.py: T1's registered rule over hand-made timings and per-pair scores."""

from __future__ import annotations

import json
from pathlib import Path

from pipelines.studies import time_trade as t1


def _pair(i: int, epe: float, teacher: float = 1.0, photo: float = 0.1) -> dict:
    # 100 PVM pixels of error epe each, 100 teacher pixels of error teacher, 100 photometric samples of photo
    return {"frame_id": f"p{i}", "pvm_n": 100, "pvm_err": 100 * epe, "pvm_bad": 0, "teacher_n": 100,
            "teacher_err": 100 * teacher, "teacher_bad": 0, "photo_sum": 100 * photo, "photo_n": 100}


def _write(out: Path, name: str, epes: list[float], teacher: float = 1.0) -> None:
    pairs = [_pair(i, e, teacher) for i, e in enumerate(epes)]
    n = len(pairs)
    summary = {"pvm_bad3": 0.0, "pvm_epe": sum(epes) / n, "teacher_bad3": 0.0, "teacher_epe": teacher,
               "photometric": 0.1, "pairs": float(n)}
    (out / "val" / name).mkdir(parents=True)
    (out / "val" / name / "gtfree.json").write_text(json.dumps({"summary": summary, "pairs": pairs}))


def _timing(out: Path, ratios: dict[str, float]) -> None:
    doc = {}
    for name, ratio in ratios.items():
        scale, rest = name[1:].split("_n")
        iters, _, refine = rest.partition("_")
        doc[name] = {"scale": float(scale), "iters": int(iters), "refine": refine or "none", "s_per_frame": ratio,
                     "sgbm_s": 1.0, "ratio": ratio}
    (out / "timing.json").write_text(json.dumps(doc))


def test_grid_starts_with_today_and_holds_every_setting_once() -> None:
    grid = t1.settings()
    assert grid[0] == t1.TODAY and len(grid) == len(set(grid)) == len(t1.SCALES) * len(t1.ITERS)
    assert t1.Setting(1.125, 4).name == "s1.125_n4" and t1.TODAY.name == "s1_n8"
    t2 = t1.settings("wmedian")  # today's default, then the scale-1 settings with the filter
    assert [s.name for s in t2] == ["s1_n8", "s1_n3_wmedian", "s1_n4_wmedian", "s1_n6_wmedian", "s1_n8_wmedian"]


def test_accuracy_pick_is_the_lowest_eligible_epe_beyond_the_noise(tmp_path: Path) -> None:
    base = [0.50, 0.52, 0.48, 0.51, 0.49]
    _timing(tmp_path, {"s1_n8": 2.4, "s1.25_n4": 2.6, "s1.375_n8": 4.0, "s1_n4": 1.6})
    _write(tmp_path, "s1_n8", base)
    _write(tmp_path, "s1.25_n4", [e - 0.05 for e in base])  # better by 0.05 on every pair: zero spread
    _write(tmp_path, "s1.375_n8", [e - 0.10 for e in base])  # better still, but over the 3.0x budget
    _write(tmp_path, "s1_n4", base)
    result = t1.table(tmp_path, "val")
    assert result["best_eligible"] == "s1.25_n4"
    assert result["accuracy_candidate"] == "s1.25_n4"
    assert result["speed_candidate"] is None  # only asked when no accuracy candidate exists
    assert (tmp_path / "table_val.md").read_text().count("over budget") == 1


def test_without_an_accuracy_candidate_the_fastest_setting_not_worse_is_the_speed_pick(tmp_path: Path) -> None:
    base = [0.50, 0.52, 0.48, 0.51, 0.49]
    _timing(tmp_path, {"s1_n8": 2.4, "s1_n4": 1.6, "s1_n3": 1.3, "s1.125_n6": 2.5})
    _write(tmp_path, "s1_n8", base)
    _write(tmp_path, "s1_n4", [0.50, 0.51, 0.48, 0.51, 0.49])  # not worse on any pair
    _write(tmp_path, "s1_n3", [0.52, 0.54, 0.50, 0.53, 0.51])  # faster but worse
    _write(tmp_path, "s1.125_n6", [0.47, 0.53, 0.45, 0.53, 0.49])  # lowest mean EPE, but inside the noise
    result = t1.table(tmp_path, "val")
    assert result["best_eligible"] == "s1.125_n6" and result["accuracy_candidate"] is None
    assert result["speed_candidate"] == "s1_n4"


def test_a_worse_teacher_score_bars_the_speed_pick(tmp_path: Path) -> None:
    base = [0.50, 0.52, 0.48, 0.51, 0.49]
    _timing(tmp_path, {"s1_n8": 2.4, "s1_n4": 1.6})
    _write(tmp_path, "s1_n8", base)
    _write(tmp_path, "s1_n4", base, teacher=1.2)
    assert t1.table(tmp_path, "val")["speed_candidate"] is None


def test_t2_rule_reads_only_its_grid_and_has_no_speed_pick(tmp_path: Path) -> None:
    base = [0.50, 0.52, 0.48, 0.51, 0.49]
    _timing(tmp_path, {"s1_n8": 2.4, "s1_n4": 1.6, "s1_n4_wmedian": 2.9, "s1_n8_wmedian": 3.1})
    _write(tmp_path, "s1_n8", base)
    _write(tmp_path, "s1_n4", [e - 0.05 for e in base])  # T1's row: not in T2's table
    _write(tmp_path, "s1_n4_wmedian", base)
    _write(tmp_path, "s1_n8_wmedian", [e - 0.05 for e in base])  # better, but over the budget
    result = t1.table(tmp_path, "val", "wmedian")
    assert {r["setting"] for r in result["rows"]} == {"s1_n8", "s1_n4_wmedian", "s1_n8_wmedian"}
    assert result["best_eligible"] == "s1_n4_wmedian"
    assert result["accuracy_candidate"] is None and result["speed_candidate"] is None
    assert (tmp_path / "table_val_wmedian.md").exists()
