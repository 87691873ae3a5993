"""Compile the NeRF stage's CPU kernels ahead of time (`compile` command, Set Up Worker).

numba compiles a kernel the first time it runs and keeps the machine code in its cache
(NUMBA_CACHE_DIR, else `__pycache__` beside the sources). Without this, the first `train` or `render`
on a machine waits for every kernel it touches, several times the frame's own time. Training and
rendering a few steps of a tiny
scene, bounded and unbounded, runs each kernel with the argument types the real work passes, so
numba's cache answers the real calls.
"""

from __future__ import annotations

import numpy as np
import torch

from .. import backend
from .camera import Camera
from .frames import NerfDataset
from .model import NerfModel
from .renderer import render_image
from .trainer import Trainer, TrainOptions, config_for

SIZE = 16  # pixels per side of the tiny scene's photos
# Small enough to train and render in well under a second once compiled; the kernels' argument types
# do not depend on these sizes.
TINY = dict(n_levels=2, log2_table_size=10, base_resolution=4, finest_resolution=16, occ_resolution=16)


def tiny_scene(has_alpha: bool, seed: int = 0) -> NerfDataset:
    """Two random 16x16 photos of the box [-1, 1]^3: RGBA (an object) or opaque (a room around it)."""
    rng = np.random.default_rng(seed)
    box = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], dtype=np.float32)
    cams = [
        Camera.looking_at_box(box, SIZE, SIZE, direction=d, name=f"view {i}")
        for i, d in enumerate([(0.65, -0.61, 0.44), (-0.5, -0.7, 0.3)])
    ]
    images = rng.random((len(cams), SIZE, SIZE, 4), dtype=np.float32)
    images[..., 3] = np.where(images[..., 3] < 0.5, 0.0, 1.0) if has_alpha else 1.0
    return NerfDataset(
        cameras=cams,
        aabb=box,
        names=[c.name for c in cams],
        images=images,
        has_alpha=has_alpha,
        source="the compile step's tiny scene",
    )


def tiny_model(ds: NerfDataset) -> NerfModel:
    cfg = config_for(ds)
    for k, v in TINY.items():
        setattr(cfg, k, v)
    return NerfModel(cfg)


def compile_kernels() -> list[NerfModel]:
    """Train and render the tiny scene, bounded and unbounded; returns the two models (the bend stage
    compiles its kernels on them). Nothing is written but numba's cache."""
    models = []
    for has_alpha in (True, False):
        ds = tiny_scene(has_alpha)
        torch.manual_seed(0)
        model = tiny_model(ds)
        Trainer(model, ds, TrainOptions(steps=3, occ_warmup_steps=2, target_samples=1 << 10)).train(progress=False)
        model.eval()
        render_image(model, ds.cameras[0])
        models.append(model)
    return models


def has_kernels() -> bool:
    """Whether the CPU kernels run here (numba installed and not turned off by NERF_DEFORM_KERNELS)."""
    return backend.use_kernels("cpu")
