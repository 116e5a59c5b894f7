"""pipelines.studies.weight_line: the straight line between two state dicts (W1)."""

from __future__ import annotations

import pytest
import torch

from pipelines.studies.weight_line import mean_state, on_line


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


def test_mean_state_hand_values() -> None:
    start, end = _dicts()
    out = mean_state([start, end, {"w": torch.tensor([2.0, 4.0]), "n": torch.tensor([7])}])
    torch.testing.assert_close(out["w"], torch.tensor([2.0, 2.0]))
    assert out["n"].item() == 7  # integer buffers from the last state dict
    with pytest.raises(ValueError, match="no state dict"):
        mean_state([])
    with pytest.raises(ValueError, match="another shape"):
        mean_state([{"w": torch.zeros(3)}, {"w": torch.zeros(2)}])
