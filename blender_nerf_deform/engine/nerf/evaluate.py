"""Quality of a NeRF: PSNR of its renders against a dataset's images (what `eval` prints)."""

from __future__ import annotations

import numpy as np

from .renderer import render_image
from .substeps import FINAL_SUBSTEPS


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else -10.0 * np.log10(mse)


def evaluate(model, dataset, background=(1.0, 1.0, 1.0), progress=None, substeps: int = FINAL_SUBSTEPS) -> list[float]:
    """PSNR of each frame of `dataset` rendered by `model` as `render` renders it (`substeps` samples per
    step of the march), both composited on `background`."""
    bg = np.asarray(background, np.float32)
    values = []
    for n, (cam, img) in enumerate(zip(dataset.cameras, dataset.images)):
        out = render_image(model, cam, background=bg, substeps=substeps)
        gt = img[..., :3] * img[..., 3:] + (1.0 - img[..., 3:]) * bg
        values.append(psnr(out["rgb"], gt))
        if progress is not None:
            progress(n + 1, len(dataset))
    return values
