from __future__ import annotations

import json

import pytest

from pvm_labeler import ConfigError, LabelerConfig


class TestLabelerConfig:
    def test_defaults_valid(self) -> None:
        cfg = LabelerConfig().validate()
        assert cfg.k == 6 and cfg.max_disp == 192

    @pytest.mark.parametrize(
        ("kwargs", "match"),
        [
            ({"k": 0}, "--k"),
            ({"kappa1": -1.0}, "kappa1=-1.0"),
            ({"kappa2": -0.1}, "kappa2=-0.1"),
            ({"max_disp": 1}, "--max-disp"),
            ({"lr_threshold": -1}, "--lr-threshold"),
            ({"census_window": 4}, "census_window"),
            ({"paths": 5}, "paths"),
            ({"p1": 10, "p2": 5}, "p1=10"),
        ],
    )
    def test_exception(self, kwargs: dict, match: str) -> None:
        with pytest.raises(ConfigError, match=match):
            LabelerConfig(**kwargs).validate()

    def test_json_roundtrip(self) -> None:
        cfg = LabelerConfig(k=4, kappa1=0.5)
        again = LabelerConfig.from_dict(json.loads(cfg.to_json()))
        assert again == cfg

    def test_unknown_key(self) -> None:
        with pytest.raises(ConfigError, match="bogus"):
            LabelerConfig.from_dict({"bogus": 1})
