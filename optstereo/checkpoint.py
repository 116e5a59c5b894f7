"""Checkpoints: atomic save, safe load (never unpickles arbitrary objects).

A training checkpoint (``.pt``/``.pth``/``.ckpt``) is a dict of tensors and plain Python values only::

    {"format": CHECKPOINT_FORMAT, "step": int, "model": state_dict, "optimizer": state_dict,
     "scheduler": state_dict | None, "scaler": state_dict | None, "model_name": str,
     "model_config": dict, "inference_config": dict, "train_config": dict,
     "code_version": {"optstereo": str, "git_commit": str}, "rng": {"torch": ByteTensor}}

It is loaded with ``torch.load(weights_only=True)``, which refuses pickled classes/functions. A weights-only export
``.safetensors`` stores the model state dict with the model name/config and the inference settings
(``inference_config``, ``optstereo.inference.config.InferenceConfig``) as JSON metadata. Files written before that
key existed kept those settings inside ``model_config`` (``input_scale``, ``refine``, ...): loading moves them to
``LoadedCheckpoint.inference_config`` (``optstereo.models.config.split_legacy_model_dict``).

Writing goes to ``<name>.tmp`` in the same directory followed by ``os.replace`` (atomic on POSIX), so a crash never
leaves a half-written file under the final name (TIMM ``checkpoint_saver.py`` does the same).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save as safetensors_bytes
from torch import nn

from optstereo.inference.config import InferenceConfig
from optstereo.inference.int8 import read_sidecar
from optstereo.models import build_model, upgrade_model_keys
from optstereo.models.config import split_legacy_model_dict
from optstereo.version import __version__
from pvm_labeler.common.atomic import atomic_path
from pvm_labeler.common.version import git_commit

logger = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "optstereo-checkpoint-v1"
CHECKPOINT_SUFFIXES = (".pt", ".pth", ".ckpt", ".safetensors")
LAST = "last.pt"


class CheckpointError(ValueError):
    """A checkpoint file is missing, unreadable, of another format or incompatible with the model."""


def code_version() -> dict[str, str]:
    """Package version and git commit of the code (``unknown`` outside a git checkout)."""
    return {"optstereo": __version__, "git_commit": git_commit()}


def _atomic_torch_save(obj: Any, path: Path) -> None:
    with atomic_path(path, fsync=True) as tmp:
        torch.save(obj, tmp)


def unwrap(model: nn.Module) -> nn.Module:
    """The bare model under DistributedDataParallel / torch.compile wrappers."""
    while True:
        if hasattr(model, "module") and isinstance(model.module, nn.Module):
            model = model.module
        elif hasattr(model, "_orig_mod"):
            model = model._orig_mod
        else:
            return model


def model_spec(model: nn.Module) -> tuple[str, dict[str, Any]]:
    """(registry name, config dict) of a model built by optstereo.models.build_model."""
    config = getattr(unwrap(model), "config", None)
    if config is None:
        return type(unwrap(model)).__name__, {}
    values = config.to_dict() if hasattr(config, "to_dict") else dict(vars(config))
    name = values.get("name", getattr(config, "name", "optstereo"))
    return str(name), values


def model_inference(model: nn.Module) -> InferenceConfig:
    """The InferenceConfig a model carries (``model.inference_config``, set by the builders of a checkpoint and of a
    training run), ``InferenceConfig()`` for a model without one."""
    config = getattr(unwrap(model), "inference_config", None)
    return config if isinstance(config, InferenceConfig) else InferenceConfig()


def save_checkpoint(
    path: Path,
    *,
    model: nn.Module,
    step: int,
    optimizer: torch.optim.Optimizer | None = None,
    scheduler: Any | None = None,
    scaler: Any | None = None,
    train_config: dict[str, Any] | None = None,
    inference: InferenceConfig | None = None,
    world_size: int = 1,
) -> Path:
    """Atomically write a full training checkpoint to ``path`` (suffix .pt/.pth/.ckpt) and return it; ``inference``
    None = the model's own (:func:`model_inference`); ``world_size``: the processes that trained it (DDP)."""
    path = Path(path)
    if path.suffix not in CHECKPOINT_SUFFIXES[:3]:
        raise CheckpointError(f"checkpoint name must end in .pt, .pth or .ckpt, got {path.name}")
    name, model_config = model_spec(model)
    state = {
        "format": CHECKPOINT_FORMAT,
        "step": int(step),
        "model": unwrap(model).state_dict(),
        "optimizer": None if optimizer is None else optimizer.state_dict(),
        "scheduler": None if scheduler is None else scheduler.state_dict(),
        "scaler": None if scaler is None or not scaler.is_enabled() else scaler.state_dict(),
        "model_name": name,
        "model_config": model_config,
        "inference_config": (inference or model_inference(model)).to_dict(),
        "train_config": train_config or {},
        "code_version": code_version(),
        "rng": {"torch": torch.get_rng_state()},
        "world_size": int(world_size),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    _atomic_torch_save(state, path)
    return path


def export_safetensors(path: Path, model: nn.Module, step: int | None = None,
                       inference: InferenceConfig | None = None) -> Path:
    """Write the model weights as safetensors with the model name/config and the inference settings (JSON) in the
    metadata; ``inference`` None = the model's own (:func:`model_inference`)."""
    path = Path(path)
    name, model_config = model_spec(model)
    # safetensors refuses shared storage; contiguous clones make every tensor its own buffer.
    tensors = {k: v.detach().contiguous().clone() for k, v in unwrap(model).state_dict().items()}
    metadata = {
        "format": CHECKPOINT_FORMAT,
        "model_name": name,
        "model_config": json.dumps(model_config),
        "inference_config": json.dumps((inference or model_inference(model)).to_dict()),
        "step": str(step if step is not None else -1),
        "code_version": json.dumps(code_version()),
    }
    # The bytes, written by us: safetensors' save_file writes through a private temp file of mode 0600, which the
    # rename would keep (every other file of a run gets the umask's mode, 0644 under umask 022).
    data = safetensors_bytes(tensors, metadata=metadata)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


@dataclass
class LoadedCheckpoint:
    """What load_checkpoint returns; optimizer/scheduler states are None in a safetensors export.

    ``model_config`` holds the architecture only and ``inference_config`` how to run it, in files of any age.
    """

    path: Path
    step: int
    model_name: str
    model_config: dict[str, Any]
    model_state: dict[str, torch.Tensor]
    inference_config: InferenceConfig = dataclasses.field(default_factory=InferenceConfig)
    optimizer: dict[str, Any] | None = None
    scheduler: dict[str, Any] | None = None
    scaler: dict[str, Any] | None = None
    train_config: dict[str, Any] | None = None
    code_version: dict[str, str] | None = None
    rng: dict[str, Any] | None = None
    world_size: int | None = None  # the training processes; None in weights files and older checkpoints


def resolve_checkpoint(path: Path) -> Path:
    """A checkpoint file, or a run directory (-> its last.pt, else its newest training checkpoint, else its newest
    weights file). A training checkpoint (.pt/.pth/.ckpt) wins over a newer weights-only export (.safetensors): it
    holds the optimiser and the step, so ``--resume`` continues instead of starting from the export and stopping."""
    path = Path(path)
    if path.is_dir():
        if (path / LAST).is_file():
            return path / LAST
        found = sorted((p for p in path.iterdir() if p.suffix in CHECKPOINT_SUFFIXES),
                       key=lambda p: (p.suffix != ".safetensors", p.stat().st_mtime))
        if not found:
            raise CheckpointError(f"no checkpoint ({'/'.join(CHECKPOINT_SUFFIXES)}) in run directory {path}")
        return found[-1]
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    if path.suffix == ".onnx":
        raise CheckpointError(f"checkpoint {path} is an exported ONNX graph, not a checkpoint: give the "
                              ".pt/.safetensors it was exported from (optstereo-predict --backend onnxruntime runs "
                              "the graph itself)")
    if path.suffix not in CHECKPOINT_SUFFIXES:
        raise CheckpointError(f"checkpoint {path} must end in one of {CHECKPOINT_SUFFIXES}")
    return path


def load_checkpoint(path: Path, map_location: str | torch.device = "cpu") -> LoadedCheckpoint:
    """Load a checkpoint file or run dir without unpickling code (weights_only=True / safetensors)."""
    path = resolve_checkpoint(path)
    if path.suffix == ".safetensors":
        return _load_safetensors(path, map_location)
    _check_torch_container(path)
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        # weights_only=True refuses anything but tensors and plain containers: never execute pickled code.
        raise CheckpointError(f"refusing to load {path}: it holds pickled objects ({exc})") from exc
    except (RuntimeError, EOFError, OSError, ValueError) as exc:
        raise CheckpointError(f"cannot load checkpoint {path}: {exc}") from exc
    if not isinstance(state, dict) or "model" not in state:
        raise CheckpointError(f"{path} is not an optstereo checkpoint (no 'model' entry)")
    if state.get("format", CHECKPOINT_FORMAT) != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path} has format {state.get('format')!r}, expected {CHECKPOINT_FORMAT!r}")
    model_config, inference = split_configs(path, str(state.get("model_name", "optstereo")),
                                            dict(state.get("model_config") or {}), state.get("inference_config"))
    return LoadedCheckpoint(
        path=path,
        step=int(state.get("step", 0)),
        model_name=str(state.get("model_name", "optstereo")),
        model_config=model_config,
        model_state=state["model"],
        inference_config=inference,
        optimizer=state.get("optimizer"),
        scheduler=state.get("scheduler"),
        scaler=state.get("scaler"),
        train_config=state.get("train_config"),
        code_version=state.get("code_version"),
        rng=state.get("rng"),
        world_size=state.get("world_size"),
    )


def _check_torch_container(path: Path) -> None:
    """Raise a CheckpointError naming ``path`` unless it is a whole zip archive, the container torch.save writes.

    Without this a random file reaches the weights-only unpickler, whose refusal reads as "pickled objects", and a
    truncated one gets miniz's internal message.
    """
    with path.open("rb") as fh:
        head = fh.read(4)
    if head[:1] != b"\x80" and not zipfile.is_zipfile(path):  # b"\x80": torch's legacy (pre-1.6) pickle format
        size = path.stat().st_size
        what = "truncated (its zip directory is missing)" if head == b"PK\x03\x04" else "not a torch checkpoint"
        raise CheckpointError(f"cannot load checkpoint {path} ({size} bytes): {what}; torch.save writes zip archives")
    if head[:1] != b"\x80":
        with zipfile.ZipFile(path) as archive:
            scripted = any(name.endswith("/constants.pkl") or "/code/" in name for name in archive.namelist())
        if scripted:  # torch.load's own refusal suggests weights_only=False, i.e. running the file's code
            raise CheckpointError(f"{path} is an exported TorchScript graph (optstereo-export --format torchscript), "
                                  "not a checkpoint: load it with torch.jit.load (its settings: the extra file "
                                  "inference_config.json), or give the .pt/.safetensors it was exported from")


def _load_safetensors(path: Path, map_location: str | torch.device) -> LoadedCheckpoint:
    try:
        with safe_open(str(path), framework="pt", device=str(map_location)) as fh:
            metadata = fh.metadata() or {}
            tensors = {k: fh.get_tensor(k) for k in fh.keys()}
    except (SafetensorError, OSError) as exc:
        raise CheckpointError(f"cannot load safetensors checkpoint {path}: {exc}") from exc
    stored = metadata.get("inference_config")
    model_config, inference = split_configs(path, metadata.get("model_name", "optstereo"),
                                            json.loads(metadata.get("model_config", "{}")),
                                            None if stored is None else json.loads(stored))
    return LoadedCheckpoint(
        path=path,
        step=int(metadata.get("step", -1)),
        model_name=metadata.get("model_name", "optstereo"),
        model_config=model_config,
        model_state=tensors,
        inference_config=inference,
        code_version=json.loads(metadata.get("code_version", "{}")),
    )


def split_configs(path: Path, name: str, model_config: dict[str, Any],
                  stored: dict[str, Any] | None) -> tuple[dict[str, Any], InferenceConfig]:
    """(architecture dict, InferenceConfig) of a file's ``model_config`` and its ``inference_config`` (None in files
    written before it existed, whose inference settings sit in ``model_config``: split_legacy_model_dict). The old
    keys of model ``name``'s config class are upgraded (``optstereo.models.upgrade_model_keys``): HITNet's
    ``feature_dim`` -> ``feature_channels``, ``max_disp`` -> ``search_range``, ...; OptStereo's ``max_disp`` /
    ``search_range``, which it never read, are dropped."""
    model_config, legacy = split_legacy_model_dict(model_config)
    try:
        model_config = upgrade_model_keys(name, model_config, f"{path}: model_config")
    except ValueError as exc:
        raise CheckpointError(str(exc)) from exc
    try:
        return model_config, InferenceConfig.from_dict({**legacy, **(stored or {})})
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{path}: bad inference settings: {exc}") from exc


def build_model_from_checkpoint(
    ckpt: LoadedCheckpoint | Path, device: str | torch.device = "cpu", **overrides: Any
) -> nn.Module:
    """Rebuild the registry model recorded in a checkpoint, load its weights, move to device, eval mode.

    ``overrides`` are fields of the model's config class (e.g. ``iters``). The model carries the file's inference
    settings as ``model.inference_config`` (an InferenceConfig), which ``optstereo.inference.engine.run`` uses by
    default.
    """
    if not isinstance(ckpt, LoadedCheckpoint):
        ckpt = load_checkpoint(ckpt)
    kwargs = {k: v for k, v in ckpt.model_config.items() if k != "name"}
    kwargs.update(overrides)
    model = build_model(ckpt.model_name, **kwargs)
    missing = sorted(model.state_dict().keys() - ckpt.model_state.keys())
    unexpected = sorted(ckpt.model_state.keys() - model.state_dict().keys())
    if missing or unexpected:  # another model's weights: name a few keys, not torch's list of every one
        raise CheckpointError(f"weights in {ckpt.path} do not fit model {ckpt.model_name!r}: {len(missing)} missing "
                              f"keys {missing[:3]}, {len(unexpected)} unexpected keys {unexpected[:3]}")
    try:
        model.load_state_dict(ckpt.model_state)
    except RuntimeError as exc:
        raise CheckpointError(f"weights in {ckpt.path} do not fit model {ckpt.model_name!r}: {exc}") from exc
    model.inference_config = ckpt.inference_config
    # the int8 clips beside a weights file (None without one: read_sidecar checks it exists)
    model.int8_calibration = None if ckpt.path is None else read_sidecar(Path(ckpt.path))
    return model.to(device).eval()


def average_checkpoints(paths: list[Path]) -> LoadedCheckpoint:
    """The uniform average of the weights of several checkpoints of one model (a "model soup").

    Every checkpoint must hold the same model name, config and state-dict keys/shapes (else a CheckpointError
    naming what differs). Floating tensors are averaged in float64 and cast back to their dtype; other tensors
    (integer counters) must be equal. Only meaningful for nearby weights (one run's end points, or a run and its
    continuations) and for models without running statistics to re-estimate (OptStereo: instance norm only).
    Returns a LoadedCheckpoint whose ``step`` is the largest of the inputs' steps.
    """
    if len(paths) < 2:
        raise CheckpointError(f"averaging needs at least two checkpoints, got {len(paths)}")
    ckpts = [load_checkpoint(p) for p in paths]
    first = ckpts[0]
    for other in ckpts[1:]:
        _check_same_model(first, other)
    state: dict[str, torch.Tensor] = {}
    for key, ref in first.model_state.items():
        values = [c.model_state[key] for c in ckpts]
        if ref.is_floating_point():
            state[key] = (sum(v.double() for v in values) / len(values)).to(ref.dtype)
        elif all(torch.equal(ref, v) for v in values[1:]):
            state[key] = ref.clone()
        else:
            raise CheckpointError(f"non-float tensor {key!r} differs between {first.path} and the others")
    return LoadedCheckpoint(path=first.path, step=max(c.step for c in ckpts), model_name=first.model_name,
                            model_config=dict(first.model_config), model_state=state,
                            inference_config=first.inference_config)


def _check_same_model(a: LoadedCheckpoint, b: LoadedCheckpoint) -> None:
    """Raise a CheckpointError naming what differs between two checkpoints' models."""
    if a.model_name != b.model_name:
        raise CheckpointError(f"{a.path} holds {a.model_name!r}, {b.path} holds {b.model_name!r}")
    diff = sorted(k for k in a.model_config.keys() | b.model_config.keys()
                  if a.model_config.get(k) != b.model_config.get(k))
    if diff:
        raise CheckpointError(f"model config of {a.path} and {b.path} differs in {diff}")
    missing = sorted(a.model_state.keys() ^ b.model_state.keys())
    if missing:
        raise CheckpointError(f"{a.path} and {b.path} have different weight keys: {missing[:5]}")
    shapes = [k for k in a.model_state if a.model_state[k].shape != b.model_state[k].shape]
    if shapes:
        raise CheckpointError(f"{a.path} and {b.path} differ in the shapes of {shapes[:5]}")


def weights_digest(model: nn.Module) -> str:
    """sha256 (16 hex digits) of the model's parameters and buffers, in name order: equal weights, equal digest,
    whatever file or inference settings they came with."""
    digest = hashlib.sha256()
    for name, tensor in sorted(model.state_dict().items()):
        digest.update(name.encode())
        digest.update(tensor.detach().to("cpu").contiguous().numpy().tobytes())
    return digest.hexdigest()[:16]
