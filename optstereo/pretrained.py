"""The shipped models: ``--checkpoint pretrained`` (one pass, the default) / ``pretrained-accurate`` (version 14,
three passes) (CLIs) and ``resolve_checkpoint_spec(name)`` (Python).

Every weight file was trained only on PVM pseudo-labels of unlabelled driving pairs (no GT frame); what, how and how
well is in the model card beside each file in ``optstereo/weights/`` (KITTI data: CC BY-NC-SA 3.0).
"""

from __future__ import annotations

from pathlib import Path

from optstereo.checkpoint import CheckpointError

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
#: Shipped name -> its weights file in WEIGHTS_DIR (each file records its own inference settings).
SHIPPED: dict[str, str] = {
    "pretrained": "optstereo_pvm_distill.safetensors",
    "pretrained-accurate": "optstereo_kitti_pvm.safetensors",
}
#: Names that were planned and did not ship, with why (a clear error instead of "file not found").
NOT_SHIPPED: dict[str, str] = {
    "pretrained-fast": "no fast model qualified (RESULTS.md, 'Candidates scored': all three fast candidates were "
                       "less accurate than dense SGM on KITTI 2015); use 'pretrained', or 'pretrained' with --scale "
                       "0.5 (about 4x faster, less accurate)",
}
PRETRAINED = "pretrained"
WEIGHTS = WEIGHTS_DIR / SHIPPED[PRETRAINED]
MODEL_CARD = WEIGHTS_DIR / "MODEL_CARD.md"


def resolve_checkpoint_spec(spec: str | Path) -> Path:
    """A shipped name (:data:`SHIPPED`) -> its safetensors file; anything else -> that path (which must exist).

    Raises:
        CheckpointError: the path does not exist, or the package was installed without its weights.
    """
    if str(spec) in SHIPPED:
        path = WEIGHTS_DIR / SHIPPED[str(spec)]
        if not path.is_file():
            raise CheckpointError(f"the shipped weights {spec!r} are missing from this installation: {path}")
        return path
    if str(spec) in NOT_SHIPPED:
        raise CheckpointError(f"'{spec}' is not shipped: {NOT_SHIPPED[str(spec)]}")
    path = Path(spec)
    if not path.exists():
        raise CheckpointError(f"checkpoint {path} does not exist (give a file, a run directory or one of "
                              f"{', '.join(SHIPPED)})")
    return path
