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
            # 0 and NaN labelled nothing (density 0 %, exit 0); a huge seed failed in h5py after config.yaml was written
            ({"kappa1": 0.0}, r"must be > 0 \(a pixel is kept where C1 < kappa1"),
            ({"kappa2": 0}, "kappa2=0"),
            ({"kappa1": float("nan")}, "kappa1 must be a finite number, got nan"),
            ({"lr_threshold": float("nan")}, "lr_threshold must be a finite number"),
            ({"seed": 10**20}, r"--seed must be in \[0, 2\^63\)"),
            ({"seed": -1}, "--seed"),
            ({"max_disp": 1}, "--max-disp"),
            ({"lr_threshold": -1}, "--lr-threshold"),
            ({"census_window": 4}, "census_window"),
            ({"paths": 5}, "paths"),
            ({"p1": 10, "p2": 5}, "p1=10"),
            # the kernels' limits (config.py constants), rejected here before a job writes anything
            ({"census_window": 9}, r"census_window must be one of \(3, 5, 7\)"),
            ({"census_window": 1}, "census_window"),
            ({"p1": -1}, "p1=-1"),
            ({"p2": 20000, "paths": 4}, r"C_max \+ p2 < 16383"),
            ({"p2": 8168}, r"p2=8168 too large for 8 paths"),  # 8 x (24 + 8168) = 65536
            ({"census_window": 7, "p2": 8144}, "overflows the uint16 cost sum"),  # 8 x (48 + 8144) = 65536
            ({"max_disp": 65505}, r"--max-disp must be in \[2, 65504\]"),
            ({"k": 2.5}, "k must be an integer, got 2.5"),
            ({"max_disp": 64.0}, "max_disp must be an integer"),
            ({"census_window": True}, "census_window must be an integer"),
            ({"min_texture": 256}, "min_texture"),
            ({"min_confidence": 1.5}, "min_confidence"),
            ({"label_mode": "vote"}, "label_mode"),
            ({"upsample": "cubic"}, "upsample"),
        ],
    )
    def test_exception(self, kwargs: dict, match: str) -> None:
        with pytest.raises(ConfigError, match=match):
            LabelerConfig(**kwargs).validate()

    @pytest.mark.parametrize(("kwargs"), [{"p2": 8167}, {"census_window": 7, "p2": 8143}, {"paths": 4, "p2": 16358},
                                          {"max_disp": 65504}, {"p1": 0, "p2": 0}])
    def test_limits_inclusive(self, kwargs: dict) -> None:
        LabelerConfig(**kwargs).validate()  # the largest values the kernels take

    def test_json_roundtrip(self) -> None:
        cfg = LabelerConfig(k=4, kappa1=0.5)
        again = LabelerConfig.from_dict(json.loads(cfg.to_json()))
        assert again == cfg

    def test_hashable_like_its_equality(self) -> None:
        """A config with its ``extra`` dict keys a dict: equal configs hash alike, a changed field or extra not."""
        a, b = LabelerConfig(extra={"run": 1}), LabelerConfig(extra={"run": 1})
        assert a == b and hash(a) == hash(b) and {a: "x"}[b] == "x"
        assert len({a, LabelerConfig(extra={"run": 2}), LabelerConfig(k=3, extra={"run": 1})}) == 3
        # equal as == has them: an int where the CLI gives a float (kappa1 2 vs 2.0), in extra too
        assert {LabelerConfig(kappa1=2, extra={"w": [1]}): "x"}[LabelerConfig(kappa1=2.0, extra={"w": [1.0]})] == "x"

    def test_unknown_key(self) -> None:
        with pytest.raises(ConfigError, match="bogus"):
            LabelerConfig.from_dict({"bogus": 1})


def test_numpy_scalars_are_the_numbers_they_equal() -> None:
    """np.int64(64) from a computed max_disp was refused ("max_disp must be an integer, got np.int64(64)"), as
    build_model(iters=np.int64(4)) was; they become plain numbers, which serialise."""
    import json

    import numpy as np

    from optstereo.models import build_model

    cfg = LabelerConfig(max_disp=np.int64(64), kappa1=np.float32(2.0), seed=np.uint8(3)).validate()
    assert (type(cfg.max_disp), type(cfg.kappa1), type(cfg.seed)) == (int, float, int)
    assert json.loads(cfg.to_json())["max_disp"] == 64
    model = build_model("optstereo", iters=np.int64(2), feature_dim=np.int64(32), hidden_dim=32, head_dim=32,
                        upsample_dim=16)
    assert type(model.config.iters) is int and type(model.config.feature_dim) is int
    with pytest.raises(ConfigError, match="max_disp must be an integer"):
        LabelerConfig(max_disp=np.float64(64.5)).validate()
