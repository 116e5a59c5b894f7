"""The shipped model: ``--checkpoint pretrained`` (CLIs) and ``resolve_checkpoint_spec("pretrained")`` (Python).

The weights are OptStereo trained only on PVM pseudo-labels of unlabelled KITTI driving pairs; what, how and how
well is in ``optstereo/weights/MODEL_CARD.md`` (KITTI data: CC BY-NC-SA 3.0).
"""

from __future__ import annotations

from pathlib import Path

from optstereo.checkpoint import CheckpointError

PRETRAINED = "pretrained"
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
WEIGHTS = WEIGHTS_DIR / "optstereo_kitti_pvm.safetensors"
MODEL_CARD = WEIGHTS_DIR / "MODEL_CARD.md"


def resolve_checkpoint_spec(spec: str | Path) -> Path:
    """``"pretrained"`` -> the shipped safetensors file; anything else -> that path (which must exist).

    Raises:
        CheckpointError: the path does not exist, or the package was installed without its weights.
    """
    if str(spec) == PRETRAINED:
        if not WEIGHTS.is_file():
            raise CheckpointError(f"the shipped weights are missing from this installation: {WEIGHTS}")
        return WEIGHTS
    path = Path(spec)
    if not path.exists():
        raise CheckpointError(f"checkpoint {path} does not exist (give a file, a run directory or 'pretrained')")
    return path
