"""Training data for OptStereo: the HDF5 shard stream and its joint augmentations."""

from optstereo.data.stream import ShardStream
from optstereo.data.transforms import TrainTransform, collate_min_size, to_tensors

__all__ = ["ShardStream", "TrainTransform", "collate_min_size", "to_tensors"]
