"""CUDA: forward/backward against the CPU, fp16 with a GradScaler, bf16 autocast, L_T on the GPU, predict on cuda.

Every test is marked ``gpu`` and skipped where CUDA is absent (CI, this project's CPU machines); run them on a GPU
machine with ``python -m pytest -m gpu tests/test_gpu.py``.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import TINY, make_shards, tiny_config

from optstereo.inference.engine import infer
from optstereo.models import build_model
from optstereo.training import loop
from optstereo.training.analogy import AnalogyConfig, transform_batch

pytestmark = [pytest.mark.gpu,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]

CUDA = torch.device("cuda")


def _tiny_model(seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)
    return build_model("optstereo", iters=3, **TINY)


def _pair(b: int = 2, h: int = 64, w: int = 128, disp: int = 5) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(0)
    base = torch.rand(b, 3, h, w + disp, generator=gen) * 255
    return base[..., :w].contiguous(), base[..., disp:disp + w].contiguous()


@pytest.fixture
def no_tf32() -> Iterator[None]:
    """CUDA convolutions default to TF32 (a 10-bit mantissa): on an H100 the stem's weight gradient then differed
    from the CPU's by ~1.5 % of its largest entry. Comparisons with the CPU run in true float32, then restore it."""
    saved = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    yield
    torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


@pytest.mark.usefixtures("no_tf32")
def test_forward_backward_matches_cpu() -> None:
    left, right = _pair()
    grads = {}
    for device in ("cpu", "cuda"):
        model = _tiny_model().to(device)
        preds = model(left.to(device), right.to(device))
        loss = sum(p.mean() for p in preds)
        loss.backward()
        grads[device] = (float(loss.detach()), {n: p.grad.detach().cpu() for n, p in model.named_parameters()})
    assert grads["cuda"][0] == pytest.approx(grads["cpu"][0], rel=1e-3)
    # a bias before a normalisation has an analytically zero gradient: both devices give rounding noise (~1e-6 on
    # an H100), so the floor of the tolerance follows the model's largest gradient, not that tensor's own
    floor = 1e-6 * max(float(g.abs().max()) for g in grads["cpu"][1].values())
    for name, g_cpu in grads["cpu"][1].items():
        g_gpu = grads["cuda"][1][name]
        assert torch.isfinite(g_gpu).all(), name
        assert torch.allclose(g_gpu, g_cpu, rtol=1e-2, atol=1e-3 * float(g_cpu.abs().max()) + floor), name


@pytest.mark.parametrize("amp", ["fp16", "bf16"])
def test_amp_training_steps(tmp_path: Path, amp: str) -> None:
    # lzf: a GPU image may lack hdf5plugin (the Blosc filter of the default compression)
    shards = make_shards(tmp_path / "shards", n=4, shard_size=2, height=64, width=136, compression="lzf")
    cfg = tiny_config(shards, tmp_path / "run", device="cuda", amp=amp, steps=6, crop=(64, 128), lambda_t=0.5)
    summary = loop.main(cfg, progress=False)
    assert summary["step"] == 6
    last = summary["last"]
    assert np.isfinite(last["L_P"]) and np.isfinite(last["L_T"])
    if amp == "fp16":  # the GradScaler ran and kept a finite scale
        ckpt = torch.load(tmp_path / "run" / "last.pt", weights_only=True)
        assert ckpt["scaler"] is not None and ckpt["scaler"]["scale"] > 0


def test_bf16_autocast_close_to_fp32() -> None:
    left, right = _pair()
    model = _tiny_model().to(CUDA).eval()
    with torch.no_grad():
        _, full32 = model(left.to(CUDA), right.to(CUDA), test_mode=True)
        with torch.autocast("cuda", dtype=torch.bfloat16):
            _, full16 = model(left.to(CUDA), right.to(CUDA), test_mode=True)
    assert full16.dtype in (torch.float32, torch.bfloat16)
    assert (full16.float() - full32).abs().mean() < 0.05 * (full32.abs().mean() + 1.0)


def test_analogy_transform_on_cuda_matches_cpu() -> None:
    left, right = _pair(h=32, w=64)
    disp = torch.full((2, 1, 32, 64), 5.0)
    cfg = AnalogyConfig(appearance=False)  # noise draws differ between devices only through .to(); keep exact
    out = {}
    for device in ("cpu", "cuda"):
        gen = torch.Generator().manual_seed(3)
        out[device] = transform_batch(left.to(device), right.to(device), disp.to(device), cfg, gen)
    assert torch.allclose(out["cuda"].target.cpu(), out["cpu"].target)
    assert torch.equal(out["cuda"].valid.cpu(), out["cpu"].valid)
    assert torch.allclose(out["cuda"].right.cpu(), out["cpu"].right, atol=1e-3)


@pytest.mark.usefixtures("no_tf32")
def test_predict_on_cuda_matches_cpu() -> None:
    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, size=(61, 133, 3), dtype=np.uint8)  # odd size: padding on both devices
    left, right = base[:, :125], base[:, 8:]
    model = _tiny_model()
    d_cpu = infer(model, left, right, device="cpu")
    d_gpu = infer(model.to(CUDA), left, right, device="cuda")
    assert d_gpu.shape == left.shape[:2]
    assert np.abs(d_gpu - d_cpu).max() < 0.05
