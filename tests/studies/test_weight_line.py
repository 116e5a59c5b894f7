"""pipelines.studies.weight_line: the straight line between two state dicts (W1)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from optstereo.checkpoint import load_checkpoint
from optstereo.pretrained import resolve_checkpoint_spec
from pipelines.studies.weight_line import arm_file, average_file, on_line


def _dicts() -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    start = {"w": torch.tensor([1.0, 2.0]), "n": torch.tensor([3])}
    end = {"w": torch.tensor([3.0, 0.0]), "n": torch.tensor([5])}
    return start, end


@pytest.mark.parametrize(("alpha", "expected"), [(0.0, [1.0, 2.0]), (1.0, [3.0, 0.0]), (0.5, [2.0, 1.0]),
                                                 (2.0, [5.0, -2.0])])
def test_on_line_hand_values(alpha: float, expected: list[float]) -> None:
    start, end = _dicts()
    out = on_line(start, end, alpha)
    torch.testing.assert_close(out["w"], torch.tensor(expected))
    assert out["n"].item() == 5  # integer buffers are not interpolated: taken from the end


def test_on_line_refuses_mismatch() -> None:
    start, end = _dicts()
    with pytest.raises(ValueError, match="keys"):
        on_line({"w": start["w"]}, end, 0.5)
    with pytest.raises(ValueError, match="shapes"):
        on_line({"w": torch.zeros(3), "n": start["n"]}, end, 0.5)


def test_the_average_of_two_arms_is_their_midpoint(tmp_path: Path) -> None:
    """theta(0.5) and theta(1.5) average to theta(1) = version 15's weights (float rounding only), and the average
    file carries version 15's inference settings."""
    out = average_file([arm_file(tmp_path, 0.5), arm_file(tmp_path, 1.5)], tmp_path / "avg.safetensors")
    avg, v15 = load_checkpoint(out), load_checkpoint(resolve_checkpoint_spec("pretrained"))
    assert avg.inference_config == v15.inference_config
    for key, ref in v15.model_state.items():
        torch.testing.assert_close(avg.model_state[key], ref, atol=1e-6, rtol=0)
