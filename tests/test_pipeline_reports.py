"""Report plumbing of pipelines/: a partial `make bench` keeps the other sections, the export bench's paired
ratios, the demo's amp choice."""

from __future__ import annotations

import json
import types
from pathlib import Path

import numpy as np
import pytest

from pipelines import bench


def _fake_section(title: str, value: int) -> types.ModuleType:
    mod = types.ModuleType(f"fake_{title}")
    mod.run = lambda shared: {"title": title, "results": {"value": value}, "markdown": f"body of {title}"}
    return mod


def test_feature_bench_only_keeps_other_sections(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    modules = {"pipelines.bench_labeler": _fake_section("Labeler", 1), "pipelines.bench_job": _fake_section("Job", 2)}
    monkeypatch.setattr(bench.importlib, "import_module", lambda name: modules[name])
    bench.main(["--out", str(tmp_path), "--only", "labeler,job"])
    modules["pipelines.bench_job"] = _fake_section("Job", 3)
    bench.main(["--out", str(tmp_path), "--only", "job"])
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["sections"] == {"labeler": {"value": 1}, "job": {"value": 3}}
    md = (tmp_path / "report.md").read_text()
    assert md.index("## Labeler") < md.index("## Job")  # SECTIONS order, not run order
    assert "body of Labeler" in md and md.count("measured at commit") == 2


def test_exception_bench_report_from_before_stamps_is_replaced(tmp_path: Path) -> None:
    (tmp_path / "report.json").write_text(json.dumps({"meta": {}, "sections": {"labeler": {"value": 1}}}))
    assert bench._load_report(tmp_path / "report.json") == {"sections": {}, "section_meta": {}}
    (tmp_path / "report.json").write_text("{not json")
    assert bench._load_report(tmp_path / "report.json") == {"sections": {}, "section_meta": {}}


def test_bench_export_paired_ratios_by_hand() -> None:
    from pipelines.bench_export import _timings, paired_ratios

    # ratios 0.8/1.0, 1.2/1.5, 0.9/1.0 = 0.8, 0.8, 0.9 -> min 0.8, median 0.8, max 0.9
    spread = paired_ratios([0.8, 1.2, 0.9], [1.0, 1.5, 1.0])
    assert spread == pytest.approx({"min": 0.8, "median": 0.8, "max": 0.9})
    with pytest.raises(ValueError, match="equally long"):
        paired_ratios([1.0], [1.0, 2.0])
    calls: list[str] = []
    times = _timings({"a": lambda: calls.append("a"), "b": lambda: calls.append("b")}, repeats=2)
    assert calls == ["a", "b", "a", "b", "a", "b"]  # one warm-up each, then alternating
    assert [len(v) for v in times.values()] == [2, 2]
    calls.clear()
    _timings({"a": lambda: calls.append("a"), "b": lambda: calls.append("b")}, repeats=1, warmup=False)
    assert calls == ["a", "b"]  # the caller already warmed them up


@pytest.mark.parametrize(("native", "choice", "expected"), [(True, "auto", "bf16"), (False, "auto", "none"),
                                                            (True, "none", "none"), (False, "bf16", "bf16")])
def test_demo_trains_in_bf16_only_where_the_cpu_has_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                       native: bool, choice: str, expected: str) -> None:
    from pipelines import demo

    class Stop(Exception):
        pass

    commands: list[list[str]] = []

    def fake_run(cmd: list[str], log: Path) -> None:
        commands.append(cmd)
        if Path(cmd[0]).name == "optstereo-train":
            raise Stop

    monkeypatch.setattr(demo, "cpu_has_native_bf16", lambda: native)
    monkeypatch.setattr(demo, "_run", fake_run)
    with pytest.raises(Stop):
        demo.main(["--out", str(tmp_path), "--amp", choice])
    train = commands[-1]
    assert train[train.index("--amp") + 1] == expected


def test_bench_models_ratio_is_per_frame_and_multi_pass_models_run_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """cpu_rows: the ratio is the median of per-frame (model / SGBM) times, the engineered path in float32, without
    Winograd and the plain one timed beside it; a model of several passes is timed once."""
    import itertools

    from optstereo.inference.config import InferenceConfig
    from pipelines import bench_models

    clock = itertools.count()
    calls: list[str] = []

    class Fake:
        def __init__(self, passes_config: InferenceConfig) -> None:
            self.inference_config = passes_config

    def fake_seconds(fn: object, repeats: int) -> float:
        func = getattr(fn, "func", None)
        names = {bench_models_infer: "model", bench_models.float32_infer: "float32",
                 bench_models.winograd_infer: "winograd", bench_models.direct_infer: "direct",
                 bench_models.plain_infer: "plain"}
        name = names.get(func, "sgbm")
        calls.append(f"{name}:{repeats}")
        return 3.0 + next(clock) if name == "model" else {"sgbm": 2.0, "float32": 5.0, "winograd": 6.0,
                                                           "direct": 8.0, "plain": 10.0}[name]

    def bench_models_infer(*args: object) -> None:  # stands for optstereo.inference.engine.infer
        raise AssertionError("timed through fake_seconds only")

    monkeypatch.setattr(bench_models, "infer", bench_models_infer)
    monkeypatch.setattr(bench_models, "_seconds", fake_seconds)
    frames = [(np.zeros((8, 16, 3), np.uint8), np.zeros((8, 16, 3), np.uint8))] * 3
    models = {"pretrained": Fake(InferenceConfig()), "accurate": Fake(InferenceConfig(coarse_start=True))}
    rows = bench_models.cpu_rows(models, frames, repeats=3)
    # model times 3, 4, 5 s against SGBM's 2 s: ratios 1.5, 2.0, 2.5 -> median 2.0; then 6, 7, 8 -> 3.5
    assert [r["ratio"] for r in rows] == [2.0, 3.5]
    assert [(r["float32_ratio"], r["winograd_ratio"], r["direct_ratio"], r["plain_ratio"])
            for r in rows] == [(2.5, 3.0, 4.0, 5.0)] * 2
    assert rows[0]["verdict"] == "met" and rows[1]["target"] is None
    assert [r["int8"] for r in rows] == [False, False]  # the fakes have no int8 clips
    assert calls[:6] == ["sgbm:3", "model:3", "float32:3", "winograd:3", "direct:3", "plain:3"]
    assert calls[-6:] == ["sgbm:1", "model:1", "float32:1", "winograd:1", "direct:1", "plain:1"]


def test_beside_sgbm_times_each_frame_after_sgbm(monkeypatch: pytest.MonkeyPatch) -> None:
    """beside_sgbm (T1's and E1's timing): SGBM then the model on each frame; medians and the per-frame ratio."""
    from pipelines import bench_models

    calls: list[str] = []
    model_times, sgbm_times = iter([3.0, 9.0, 5.0]), iter([1.0, 3.0, 2.0])

    class Sgbm:
        def compute(self, left: np.ndarray, right: np.ndarray) -> None:
            raise AssertionError("timed through fake_seconds only")

    sgbm = Sgbm()

    def fake_seconds(fn: object, repeats: int) -> float:
        is_sgbm = getattr(fn, "func", None) == sgbm.compute
        calls.append("sgbm" if is_sgbm else "model")
        return next(sgbm_times) if is_sgbm else next(model_times)

    monkeypatch.setattr(bench_models, "_seconds", fake_seconds)
    frames = [(np.zeros((8, 16, 3), np.uint8), np.zeros((8, 16, 3), np.uint8))] * 3
    row = bench_models.beside_sgbm(object(), frames, 2, sgbm)  # type: ignore[arg-type]
    # ratios 3.0, 3.0, 2.5 -> median 3.0; model times median 5.0, SGBM's 2.0
    assert row == {"s_per_frame": 5.0, "sgbm_s": 2.0, "ratio": 3.0}
    assert calls == ["sgbm", "model"] * 3

    def custom(model: object, left: np.ndarray, right: np.ndarray) -> None:  # e.g. infer with amp="bf16"
        """A stand-in for the pass to time."""

    timed: list[object] = []
    monkeypatch.setattr(bench_models, "_seconds", lambda fn, repeats: timed.append(fn.func) or 1.0)
    assert bench_models.beside_sgbm(object(), frames[:1], 1, sgbm, run=custom)["ratio"] == 1.0  # type: ignore[arg-type]
    assert timed == [sgbm.compute, custom]


def test_bench_models_match_row(monkeypatch: pytest.MonkeyPatch) -> None:
    """match_row: per-frame (match / SGBM) ratio, median, against the 0.5 target; bad-3 pooled over the scored ones."""
    import itertools

    from pipelines import bench_models

    clock = itertools.count()

    def fake_seconds(fn: object, repeats: int) -> float:
        return 2.0 if getattr(fn, "func", None) is not bench_models._match else 0.8 + 0.2 * next(clock)

    gt = np.array([[10.0, 10.0, 10.0, np.nan]], np.float32)
    monkeypatch.setattr(bench_models, "_seconds", fake_seconds)
    monkeypatch.setattr(bench_models, "_match", lambda left, right: np.array([[10, 10, 20, 0]], np.float32))
    monkeypatch.setattr(bench_models, "_sgbm_filled", lambda sgbm, left, right: np.full((1, 4), 20, np.float32))
    frames = [(np.zeros((1, 4, 3), np.uint8), np.zeros((1, 4, 3), np.uint8))] * 3
    row = bench_models.match_row(frames, [(*frames[0], gt)] * 2, repeats=3)
    # match 0.8, 1.0, 1.2 s against SGBM's 2 s: ratios 0.4, 0.5, 0.6 -> median 0.5, met; bad-3 2/6 vs 6/6
    assert row["ratio"] == pytest.approx(0.5) and row["verdict"] == "met"
    assert row["bad3"] == pytest.approx(100 / 3) and row["sgbm_bad3"] == 100.0


def test_bench_avx2_proxy_child_runs_capped(shared_data: Path) -> None:
    """proxy_row: the child process runs with the AVX2 caps (torch reports AVX2 on any AVX2 CPU, AVX-512 or not),
    times the model beside SGBM-HH on the frames asked for, and a failing child is an error naming the model."""
    from pipelines import bench_models

    row = bench_models.proxy_row(shared_data, "pretrained", repeats=1, n_frames=1)
    assert row["torch_capability"] == "AVX2"
    assert row["env"] == bench_models.AVX2_PROXY
    assert row["model"] == "pretrained" and row["s_per_frame"] > 0 and row["sgbm_s"] > 0
    assert row["ratio"] == pytest.approx(row["s_per_frame"] / row["sgbm_s"])  # one frame: the ratio of the two
    assert row["int8"] is True and row["float32_s_per_frame"] > 0  # the shipped default has int8 clips
    assert "AVX2 proxy" in "\n".join(bench_models._proxy_markdown(row))
    with pytest.raises(RuntimeError, match="no-such-model"):
        bench_models.proxy_row(shared_data, "no-such-model", repeats=1, n_frames=1)
