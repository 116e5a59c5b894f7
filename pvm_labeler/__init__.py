"""PVM labeler: multi-scale SGM + pyramid voting + LR check -> semi-dense pseudo-labels (no torch here)."""

from pvm_labeler.config import LabelerConfig
from pvm_labeler.errors import ConfigError, InputError, PVMError, ShardError

__all__ = ["LabelerConfig", "PVMError", "InputError", "ConfigError", "ShardError"]
__version__ = "0.1.0"
