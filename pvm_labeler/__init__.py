"""PVM labeler: multi-scale SGM + pyramid voting + LR check -> semi-dense pseudo-labels (no torch here)."""

from pvm_labeler.config import LabelerConfig
from pvm_labeler.errors import ConfigError, InputError, PVMError, ShardError
from pvm_labeler.multiscale import LabelResult, draw_eps, label_pair

__all__ = ["LabelerConfig", "PVMError", "InputError", "ConfigError", "ShardError", "LabelResult", "label_pair",
           "draw_eps"]
__version__ = "0.1.0"
