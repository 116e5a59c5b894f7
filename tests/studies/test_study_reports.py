"""Report plumbing of the studies: the training-studies report reads runs whose (git-ignored) run dirs are gone from
their committed JSONs; the shipped model's continuation stages chain, skip and resume; its lineage plot and
extrapolation."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import pytest

from pipelines.studies import train_pretrained as tp
from pipelines.studies import train_studies as ts


def test_feature_studies_report_falls_back_to_committed_json(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ts, "OUT", tmp_path / "out")
    monkeypatch.setattr(ts, "RESULTS", tmp_path / "results")
    ts.RESULTS.mkdir()
    committed = {"name": "ms_d4_main", "eval": {"bad3": 15.0}, "curve": [[10, 5.0, 4.0], [20, 3.0, 2.5]]}
    (ts.RESULTS / "ms_d4_main.json").write_text(json.dumps(committed))
    runs = ts.load_runs()
    assert list(runs) == ["ms_d4_main"] and runs["ms_d4_main"]["live"] is False
    assert runs["ms_d4_main"]["eval"]["bad3"] == 15.0
    ts.plot_curves(runs, tmp_path / "curves.png")  # drawn from the stored curve, no run dir needed
    assert (tmp_path / "curves.png").stat().st_size > 1000


def test_studies_trend_from_committed_curve(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # With the run dir gone the label-EPE trend is read from the JSON's curve (step, L_P, label EPE), so a rebuilt
    # results/training.md keeps the sentence. Hand-computed: records 0.70 before, 0.60 at the end -> still falling.
    monkeypatch.setattr(ts, "OUT", tmp_path / "out")
    curve = [[10 * (i + 1), 1.0, 0.70] for i in range(15)] + [[160 + 10 * i, 1.0, 0.60] for i in range(5)]
    text = ts._trend("ms_d4_onecycle", {"ms_d4_onecycle": {"curve": curve}})
    assert "from 0.70 px" in text and "to 0.60 px" in text and "still falling" in text
    assert ts._trend("ms_d4_onecycle", {"ms_d4_onecycle": {"curve": curve[:10]}}) == ""  # too short to say


def test_feature_claim_uses_longest_evaluated_self_supervised_run() -> None:
    assert ts.claim_pair({"ms_d4_main": {}, "ms_d4_long": {}}) == ("ms_d4_long", "gt_long", ts.LONG_STEPS)
    assert ts.claim_pair({"ms_d4_long": {}, "ms_d4_onecycle": {}})[0] == "ms_d4_onecycle"
    text = ts.claim_text({"ms_d4_onecycle": {"bad3": 9.0}, "gt_long": {"bad3": 6.5}},
                         {"sgm_dense_nan_filled": {"bad3": 10.3}, "sgm_dense_nan_as_error": {"bad3": 10.56}})
    assert "**met**" in text and f"`gt_long`, {ts.LONG_STEPS} steps" in text
    text = ts.claim_text({"ms_d4_onecycle": {"bad3": 10.4}},
                         {"sgm_dense_nan_filled": {"bad3": 10.3}, "sgm_dense_nan_as_error": {"bad3": 10.56}})
    assert "**not met**" in text


def test_continue_stages_chain_skip_and_resume(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each CONTINUE run --inits the previous run's exported weights; a finished run is skipped, a cut one resumed."""
    monkeypatch.setattr(tp, "RUNS", tmp_path)
    monkeypatch.setattr(tp, "HEADS", tmp_path / "no_heads")  # committed heads: test_init_weights_falls_back_...
    ran: list[list[str]] = []
    monkeypatch.setattr(tp, "_run", lambda cmd: ran.append([str(c) for c in cmd]))
    first, second = tp.CONTINUE[0][0], tp.CONTINUE[1][0]
    cmds = {run: [str(c) for c in cmd] for run, cmd in tp.continue_commands().items()}
    init = cmds[second][cmds[second].index("--init") + 1]
    assert init == str(tmp_path / first / "model.safetensors") and "--conf-weight" in cmds[second]
    assert cmds[first][cmds[first].index("--init") + 1] == str(tmp_path / tp.CONTINUE[0][1] / "model.safetensors")
    (tmp_path / first).mkdir()
    (tmp_path / first / "summary.json").write_text("{}")
    (tmp_path / second).mkdir()
    (tmp_path / second / "last.pt").write_bytes(b"")
    tp.step_continue()
    assert ran[0] == [str(tp.BIN / "optstereo-train"), "--resume", str(tmp_path / second), "--quiet"]
    # every later stage starts fresh from the stage before it, in order
    later = [run for run, *_ in tp.CONTINUE[2:]]
    assert [cmd[cmd.index("--out") + 1] for cmd in ran[1:]] == [str(tmp_path / run) for run in later]
    # "pretrained" starts from the shipped file (the run before it is gone), every other init from a run's export
    assert [cmd[cmd.index("--init") + 1] for cmd in ran[1:]] == [
        str(tp.WEIGHTS if init == "pretrained" else tmp_path / init / "model.safetensors")
        for _, init, *_ in tp.CONTINUE[2:]]
    assert any(init == "pretrained" for _, init, *_ in tp.CONTINUE)



def test_continue_one_stage_from_its_parents_weights(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """`continue RUN` runs only that stage, from its parent's committed head when the parent's run dir is gone; an
    unknown stage or missing starting weights is a clear error naming them, and nothing runs."""
    monkeypatch.setattr(tp, "RUNS", tmp_path / "runs")
    monkeypatch.setattr(tp, "HEADS", tmp_path / "heads")
    ran: list[list[str]] = []
    monkeypatch.setattr(tp, "_run", lambda cmd: ran.append([str(c) for c in cmd]))
    run, init = next((run, init) for run, init, *_ in tp.CONTINUE if init != "pretrained")
    with pytest.raises(ValueError, match=f"{init}.safetensors"):
        tp.step_continue(run)
    with pytest.raises(SystemExit):
        tp.main(["continue", "no_such_stage"])
    assert "no such CONTINUE stage" in capsys.readouterr().err and not ran
    head = tmp_path / "heads" / f"{init}.safetensors"
    head.parent.mkdir()
    head.write_bytes(b"")
    tp.step_continue(run)
    assert len(ran) == 1 and ran[0][ran[0].index("--out") + 1] == str(tmp_path / "runs" / run)
    assert ran[0][ran[0].index("--init") + 1] == str(head)
    (tmp_path / "runs" / run).mkdir(parents=True)
    (tmp_path / "runs" / run / "last.pt").write_bytes(b"")  # cut short: resumed, whatever its parent's weights
    head.unlink()
    tp.step_continue(run)
    assert ran[1] == [str(tp.BIN / "optstereo-train"), "--resume", str(tmp_path / "runs" / run), "--quiet"]


def test_init_weights_falls_back_to_the_committed_head(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A run's own export wins; without its directory, the committed head; neither: the export path (made earlier)."""
    monkeypatch.setattr(tp, "RUNS", tmp_path / "runs")
    monkeypatch.setattr(tp, "HEADS", tmp_path / "heads")
    assert tp.init_weights("pretrained") == tp.WEIGHTS
    export, head = tmp_path / "runs" / "a" / "model.safetensors", tmp_path / "heads" / "a.safetensors"
    assert tp.init_weights("a") == export
    head.parent.mkdir()
    head.write_bytes(b"")
    assert tp.init_weights("a") == head
    export.parent.mkdir(parents=True)
    export.write_bytes(b"")
    assert tp.init_weights("a") == export


def test_studies_report_keeps_committed_baselines(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A baseline whose eval dir is gone keeps its committed figures; the overview is kept without labels."""
    monkeypatch.chdir(tmp_path)
    results = tmp_path / "results" / "training"
    results.mkdir(parents=True)
    committed = {"pvm_labels": {"bad3": 1.02}, "sgm_dense_nan_filled": {"bad3": 10.3},
                 "sgm_dense_nan_as_error": {"bad3": 12.0, "epe": None}, "sgm_dense_valid_only": None}
    (results / "baselines.json").write_text(json.dumps(committed))
    (results / "overview.png").write_bytes(b"committed figure")
    monkeypatch.setattr(ts, "RESULTS", results)
    monkeypatch.setattr(ts, "LABELS", tmp_path / "no_labels")
    monkeypatch.setattr(ts, "load_runs", lambda: {})
    monkeypatch.setattr(ts, "eval_dir", lambda key: tmp_path / "gone" / key)
    monkeypatch.setattr(ts, "plot_curves", lambda runs, path: None)
    monkeypatch.setattr(ts, "render_markdown", lambda runs, baselines: json.dumps(baselines))
    ts.step_report()
    written = json.loads((results / "baselines.json").read_text())
    assert {k: written[k] for k in committed} == committed
    assert (results / "overview.png").read_bytes() == b"committed figure"


def test_lineage_steps_add_up_and_extrapolation_is_hand_computed(tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(tp, "LINEAGE", (("a", "", 1000, ""), ("gone", "", 500, ""), ("b", "", 500, ""),
                                        ("c", "", 2000, "")))
    doc = lambda k15: {s: {"summary": {"bad3": k15 + i}} for i, (s, *_) in enumerate(tp.EVAL_SETS)}  # noqa: E731
    points = tp.lineage_points({"a": doc(10.0), "b": doc(9.0), "c": doc(8.0)})
    # "gone" has no evaluation but its 500 steps still count towards the rows after it
    assert [(p[0], p[1], p[2]["kitti15"], p[2]["kitti12"], p[3]) for p in points] == [
        (1000, "a", 10.0, 11.0, None), (2000, "b", 9.0, 10.0, "a"), (4000, "c", 8.0, 9.0, "b")]
    assert tp.main_path(points) == points
    linear, loglinear = tp.steps_to_target(points, target=6.0)
    # least squares over (1000, 10), (2000, 9), (4000, 8): slope -3000 / 4666666.67 per step; gap 2 points
    assert linear == pytest.approx(2 * 4666666.667 / 3000, rel=1e-6)
    # exactly 1 point per doubling: 2 more points = two more doublings of 4000 steps -> 16000, i.e. 12000 more
    assert loglinear == pytest.approx(12000.0, rel=1e-9)
    assert tp.steps_to_target(points, target=8.5) is None  # already below the target
    sgm = {s: {"summary": {"bad3": 10.0}} for s, *_ in tp.EVAL_SETS}
    tp.plot_lineage(points, sgm, tmp_path / "lineage.png")
    image = cv2.imread(str(tmp_path / "lineage.png"))
    assert image is not None and image.shape[0] > 300 and image.shape[1] > 600
    assert "3,111 more steps" in tp.extrapolation_text(points, sgm_bad3=8.0)
    # target 0.75 x 11.5 = 8.625: b (9.0) misses it, c (8.0) meets it first -> named, nothing extrapolated
    met = tp.extrapolation_text(points, sgm_bad3=11.5)
    assert "met, first by `c` (8.00 % after 4,000 steps)" in met and "more steps" not in met


def test_lineage_side_branch_is_left_out_of_the_main_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A row naming its parent adds its steps to that parent's; the extrapolation follows the last row's ancestors."""
    monkeypatch.setattr(tp, "LINEAGE", (("a", "", 1000, ""), ("b", "", 1000, ""), ("side", "", 9000, ""),
                                        ("c", "", 2000, "b")))
    doc = lambda k15: {s: {"summary": {"bad3": k15}} for s, *_ in tp.EVAL_SETS}  # noqa: E731
    points = tp.lineage_points({"a": doc(10.0), "b": doc(9.0), "side": doc(7.0), "c": doc(8.0)})
    assert [(p[0], p[1], p[3]) for p in points] == [(1000, "a", None), (2000, "b", "a"), (11000, "side", "b"),
                                                  (4000, "c", "b")]
    assert [p[1] for p in tp.main_path(points)] == ["a", "b", "c"]
    # along a -> b -> c: 1 point per doubling, 2 more points to 6 % -> 16000 steps, 12000 more (the side row ignored)
    assert "12,000 at the log-linear rate" in tp.extrapolation_text(points, sgm_bad3=8.0)
    sgm = {s: {"summary": {"bad3": 10.0}} for s, *_ in tp.EVAL_SETS}
    tp.plot_lineage(points, sgm, tmp_path / "lineage.png")
    assert cv2.imread(str(tmp_path / "lineage.png")) is not None


def test_lineage_extrapolates_along_the_recipe_head_not_a_later_branch(monkeypatch: pytest.MonkeyPatch) -> None:
    """A recipe change branching off the head (listed after it) must not end the curve the extrapolation fits."""
    monkeypatch.setattr(tp, "LINEAGE", (("a", "", 1000, ""), ("b", "", 1000, ""), ("c", "", 2000, ""),
                                        ("new_recipe", "", 500, "c")))
    doc = lambda k15: {s: {"summary": {"bad3": k15}} for s, *_ in tp.EVAL_SETS}  # noqa: E731
    points = tp.lineage_points({"a": doc(10.0), "b": doc(9.0), "c": doc(8.0), "new_recipe": doc(8.5)})
    assert [p[1] for p in tp.main_path(points)] == ["a", "b", "c", "new_recipe"]  # default: the last row
    assert [p[1] for p in tp.main_path(points, "c")] == ["a", "b", "c"]
    # along a -> b -> c: 1 point per doubling, 12000 more steps to 6 %; through new_recipe the fit is another
    assert "12,000 at the log-linear rate" in tp.extrapolation_text(points, sgm_bad3=8.0, head="c")
    assert "12,000" not in tp.extrapolation_text(points, sgm_bad3=8.0, head="new_recipe")
    assert [p[1] for p in tp.main_path(points, "not evaluated")] == ["a", "b", "c", "new_recipe"]
