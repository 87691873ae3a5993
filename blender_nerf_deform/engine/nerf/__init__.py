"""The NeRF stage: datasets and cameras, the field (hash encoding + MLPs), its occupancy grid,
training, checkpoints, volume rendering and evaluation. Kernels (numba) live beside the
code they speed up: encoding_kernels, march_kernels, adam_kernels."""
