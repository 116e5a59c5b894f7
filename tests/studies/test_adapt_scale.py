"""Ninth-session studies: A5's start (pipelines/studies/adapt_scale.py) is version 15's weights with only its input
scale changed; Q1's time study (pipelines/studies/int8_time.py) reads its verdict from the runs as registered."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from optstereo.api import load_model
from optstereo.checkpoint import load_checkpoint, model_inference
from pipelines.studies import adapt_scale, int8_time


def test_start_file_changes_the_scale_only(tmp_path: Path) -> None:
    path = adapt_scale.start_file(tmp_path, 1.625)
    shipped = load_model("pretrained")
    start = load_checkpoint(path)
    assert start.inference_config.scale == 1.625
    assert start.inference_config.replace(scale=model_inference(shipped).scale) == model_inference(shipped)
    state = shipped.state_dict()
    assert all(torch.equal(state[k], v) for k, v in start.model_state.items())
    mtime = path.stat().st_mtime_ns
    assert adapt_scale.start_file(tmp_path, 1.625) == path and path.stat().st_mtime_ns == mtime  # kept on resume


@pytest.mark.parametrize("ratios, uncapped, eligible", [([1.93, 1.92, 1.87], (1.15, 1.61), (True, True)),
                                                        ([2.3, 1.9, 2.1], (1.7, 1.6), (False, False))])
def test_int8_time_verdict(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, ratios: list[float],
                           uncapped: tuple[float, float], eligible: tuple[bool, bool]) -> None:
    """Median of the proxy runs against 2.0, and int8 against float32 uncapped (seconds stand in for ratios)."""
    runs = iter(ratios)
    monkeypatch.setattr(int8_time.bench_models, "proxy_row", lambda shared, name: {"ratio": next(runs),
                                                                                    "float32_ratio": 2.5})
    monkeypatch.setattr(int8_time, "load_model", lambda name: object())
    monkeypatch.setattr(int8_time.bench_models, "_frames", lambda shared: [])
    monkeypatch.setattr(int8_time.bench_models, "_opencv", lambda mode: None)
    times = iter(uncapped)

    def beside(model: object, frames: list, repeats: int, sgbm: object, run: object = None) -> dict[str, float]:
        t = next(times)
        return {"s_per_frame": t, "ratio": t}

    monkeypatch.setattr(int8_time.bench_models, "beside_sgbm", beside)
    int8_time.main(["--out", str(tmp_path / "t.json")])
    verdict = json.loads((tmp_path / "t.json").read_text())["verdict"]
    assert (verdict["proxy_le_2"], verdict["uncapped_int8_faster"]) == eligible
    assert verdict["proxy_median_ratio"] == sorted(ratios)[1]
