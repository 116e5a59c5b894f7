"""The torch-free base both programs import on purpose.

datasets (readers of each dataset's official layout), io (images, PFM, KITTI PNG), metrics (AEPE, bad-N, D1),
viz (colour maps, error maps, plots), errors, atomic (write-to-temp-then-rename), configtools, version. Nothing
here imports torch, numba or the labeler's kernels.
"""
