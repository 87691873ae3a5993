"""Compile the bend stage's CPU kernels ahead of time (`compile` command, Set Up Worker).

As nerf/warmup.py: one frame of each tiny NeRF ray-bent through a twisted lattice cage.
"""

from __future__ import annotations

from ..geometry.warmup import bent_pose, lattice_cage
from .posed import PosedRenderer


def compile_kernels(models, camera) -> None:
    """`models`: NeRFs of the box [-1, 1]^3 (nerf.warmup's); `camera` looks at it."""
    vertices, tets = lattice_cage((-0.8, -0.8, -0.8), (0.8, 0.8, 0.8))
    for model in models:
        PosedRenderer(model, vertices, tets).render(camera, bent_pose(vertices))
