"""torchrun / DistributedDataParallel helpers: gloo on CPU, nccl on CUDA.

``torchrun --nproc_per_node N -m optstereo.cli train ...`` (or the ``optstereo-train`` script under torchrun) sets
RANK, WORLD_SIZE, LOCAL_RANK and MASTER_ADDR/PORT; ``setup`` reads them. Without those variables everything runs in
one process and these helpers are no-ops, so the same training code serves both cases.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch import nn

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class DistInfo:
    """Position of this process: rank / world_size over all nodes, local_rank on this node."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def resolve_device(name: str, local_rank: int = 0) -> torch.device:
    """"auto" -> cuda:<local_rank> when CUDA is available, else cpu; "cuda" without CUDA is an error."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda":
        if not torch.cuda.is_available():
            build = "a CPU-only build" if torch.version.cuda is None else f"built for CUDA {torch.version.cuda}"
            raise RuntimeError(f"device cuda was requested but torch.cuda.is_available() is False (torch "
                               f"{torch.__version__}, {build}): use device cpu (or auto), or install a CUDA torch")
        return torch.device("cuda", local_rank)
    if name != "cpu":
        raise ValueError(f"--device must be auto, cpu or cuda, got {name!r}")
    return torch.device("cpu")


def env_info() -> DistInfo:
    """DistInfo from torchrun's environment variables ((0, 1, 0) when absent)."""
    return DistInfo(
        rank=int(os.environ.get("RANK", 0)),
        world_size=int(os.environ.get("WORLD_SIZE", 1)),
        local_rank=int(os.environ.get("LOCAL_RANK", 0)),
    )


def setup(device: torch.device) -> DistInfo:
    """Initialise the default process group when launched by torchrun (backend: nccl on CUDA, gloo on CPU)."""
    info = env_info()
    if not info.enabled:
        return info
    if not dist.is_initialized():
        backend = "nccl" if device.type == "cuda" else "gloo"
        if device.type == "cuda":
            torch.cuda.set_device(device)
        dist.init_process_group(backend=backend, rank=info.rank, world_size=info.world_size)
        logger.info("rank %d/%d joined the %s process group", info.rank, info.world_size, backend)
    return info


def cleanup() -> None:
    """Destroy the process group if one is active."""
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


def wrap_model(model: nn.Module, device: torch.device, info: DistInfo) -> nn.Module:
    """DistributedDataParallel around ``model`` when running distributed, else the model itself.

    The parameters of every rank are made identical at construction (DDP broadcasts rank 0's state), and the
    gradient all-reduce keeps them identical after every optimiser step.
    """
    if not info.enabled:
        return model
    device_ids = [device.index] if device.type == "cuda" else None
    return nn.parallel.DistributedDataParallel(model, device_ids=device_ids)


def all_reduce_mean(values: dict[str, float], device: torch.device) -> dict[str, float]:
    """Mean of scalar logs over ranks (identity when not distributed)."""
    if not (dist.is_available() and dist.is_initialized()) or not values:
        return values
    keys = sorted(values)
    buf = torch.tensor([float(values[k]) for k in keys], dtype=torch.float64, device=device)
    dist.all_reduce(buf)
    buf /= dist.get_world_size()
    return dict(zip(keys, buf.tolist(), strict=True))


def barrier() -> None:
    """Synchronise ranks (no-op when not distributed)."""
    if dist.is_available() and dist.is_initialized():
        dist.barrier()


def param_checksum(model: nn.Module) -> float:
    """Sum of all parameters in float64: equal on every rank iff the weights are in sync (up to summation)."""
    with torch.no_grad():
        return float(sum(p.detach().double().sum().item() for p in model.parameters()))
