"""pipelines/studies/convex_head.py (U1): what the cache holds, the loss, and the exported file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from conftest import TINY, make_shards

from optstereo.api import load_model
from optstereo.checkpoint import export_safetensors
from optstereo.inference.engine import infer
from optstereo.models import build_model
from optstereo.models.optstereo import normalize_image
from optstereo.models.upsample import ConvexUpsampler
from pipelines.studies import convex_head


def _tiny_file(tmp_path: Path) -> Path:
    torch.manual_seed(0)
    return export_safetensors(tmp_path / "tiny.safetensors", build_model("optstereo", **TINY, iters=3))


def test_the_cache_holds_what_the_upsampler_gets(tmp_path: Path) -> None:
    model = load_model(_tiny_file(tmp_path))
    rng = np.random.default_rng(0)
    left, right = (rng.integers(0, 255, (37, 61, 3), dtype=np.uint8) for _ in range(2))  # padded on every side
    disp, hidden, pads = convex_head.upsampler_inputs(model, left, right)
    assert disp.shape == (5, 8) and hidden.shape == (TINY["hidden_dim"], 5, 8) and any(pads)
    image = torch.nn.functional.pad(torch.from_numpy(left).permute(2, 0, 1)[None].float(), pads, mode="replicate")
    with torch.inference_mode():
        full = model.upsampler(torch.from_numpy(disp)[None, None], torch.from_numpy(hidden.astype(np.float32))[None],
                               normalize_image(image))
    # the model's own upsampler on the cached inputs is the pass's output (h is stored in float16)
    np.testing.assert_allclose(convex_head.unpad(full, np.array(pads))[0, 0].numpy(), infer(model, left, right),
                               atol=1e-3)


def test_pair_loss_is_the_confidence_weighted_huber() -> None:
    head = ConvexUpsampler(4)
    # a constant D_s = 2 upsamples to 16 whatever the mask away from the border (the unfold pads with zeros): every
    # convex combination of equal values. Labels only there: the inner (16, 24) of (32, 40).
    label = np.full((32, 40), np.nan, np.float32)
    label[8:24, 8:32] = 16.0
    item = {"disp": np.full((4, 5), 2.0, np.float32), "hidden": np.random.default_rng(0).normal(size=(4, 4, 5))
            .astype(np.float16), "pads": np.array([0, 0, 0, 0]), "label": label,
            "confidence": np.ones((32, 40), np.float16)}
    with torch.no_grad():
        assert float(convex_head.pair_loss(head, item)) < 1e-6
    inner, weight = item["label"][8:24, 8:32], item["confidence"][8:24, 8:32]
    inner[:8] += 0.5  # half the pixels 0.5 px off: Huber 0.125 each
    inner[8:, :12] += 3.0  # a quarter 3 px off (Huber 2.5), weighted 0.5, and one pixel with no label
    weight[8:, :12] = 0.5
    inner[15, 23] = np.nan
    n_half, n_quarter, n_rest = 8 * 24, 8 * 12, 8 * 12 - 1
    want = (n_half * 0.125 + 0.5 * n_quarter * 2.5) / (n_half + 0.5 * n_quarter + n_rest)
    with torch.no_grad():
        assert abs(float(convex_head.pair_loss(head, item)) - want) < 1e-5


def test_training_resumes_and_export_keeps_every_other_weight(tmp_path: Path) -> None:
    base = _tiny_file(tmp_path)
    labels = make_shards(tmp_path / "labels", n=2, shard_size=2, height=32, width=64, with_gt=False)
    assert convex_head.cache(labels, tmp_path / "cache", base) == 2
    assert convex_head.cache(labels, tmp_path / "cache", base) == 0  # resumable: nothing left
    convex_head.train(tmp_path / "cache", tmp_path / "run", minutes=0.02)
    first = torch.load(tmp_path / "run" / "head.pt", weights_only=False)["state"]["step"]
    convex_head.train(tmp_path / "cache", tmp_path / "run", minutes=0.02)
    assert torch.load(tmp_path / "run" / "head.pt", weights_only=False)["state"]["step"] > first > 0
    out = convex_head.export(tmp_path / "run", tmp_path / "u1.safetensors", base)
    new, old = load_model(out), load_model(base)
    assert new.config.upsampler == "convex" and isinstance(new.upsampler, ConvexUpsampler)
    head = torch.load(tmp_path / "run" / "head.pt", weights_only=False)["head"]
    for key, value in new.state_dict().items():
        want = head[key.removeprefix("upsampler.")] if key.startswith("upsampler.") else old.state_dict()[key]
        assert torch.equal(value, want), key


def test_edge_band_marks_the_pixels_near_a_depth_step_only() -> None:
    from pipelines.studies import edge_band

    teacher = np.full((40, 60), 10.0, np.float32)
    teacher[:, 30:] = 30.0  # one vertical depth step between columns 29 and 30
    band = edge_band.edge_band(teacher)
    cols = np.flatnonzero(band.any(axis=0))
    # the Sobel response covers columns 29-30; the band adds RADIUS either side
    assert cols.min() == 29 - edge_band.RADIUS and cols.max() == 30 + edge_band.RADIUS
    assert band[:, cols].all() and not band[:, :20].any()


def test_the_hybrid_upsampler_starts_as_the_papers() -> None:
    from optstereo.models.upsample import ConvUpsampler

    torch.manual_seed(0)
    conv = ConvUpsampler(width=8)
    hybrid = convex_head.HybridUpsampler(conv, hidden_dim=6)
    disp, hidden = torch.rand(2, 1, 5, 7) * 10, torch.randn(2, 6, 5, 7)
    image = torch.rand(2, 3, 40, 56) * 2 - 1
    with torch.no_grad():
        assert torch.allclose(hybrid(disp, hidden, image), conv(disp, hidden, image), atol=1e-4)
        hybrid.convex.mask[2].weight.normal_()  # once the mask moves, it is another function
        assert not torch.allclose(hybrid(disp, hidden, image), conv(disp, hidden, image), atol=1e-2)
