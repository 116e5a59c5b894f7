"""OptStereo: the network and trainer of PVStereo (Wang et al.), supervised by PVM pseudo-labels."""

__version__ = "0.1.0"
