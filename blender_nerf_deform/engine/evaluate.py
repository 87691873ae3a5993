"""`eval` command: PSNR of a checkpoint over a dataset's frames (composited on white).

    python -m blender_nerf_deform.engine eval --nerf CKPT --data DIR [--downscale K] [--device D]

Prints one line per frame and a last line `PSNR <mean> dB over <n> frames`.
"""

from __future__ import annotations

import numpy as np

from .checkpoint import load_nerf
from .dataset import load_dataset
from .renderer import render_image


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else -10.0 * np.log10(mse)


def evaluate(model, dataset, background=(1.0, 1.0, 1.0), progress=None) -> list[float]:
    """PSNR of each frame of `dataset` rendered by `model`, both composited on `background`."""
    bg = np.asarray(background, np.float32)
    values = []
    for n, (cam, img) in enumerate(zip(dataset.cameras, dataset.images)):
        out = render_image(model, cam, background=bg)
        gt = img[..., :3] * img[..., 3:] + (1.0 - img[..., 3:]) * bg
        values.append(psnr(out["rgb"], gt))
        if progress is not None:
            progress(n + 1, len(dataset))
    return values


def main(args) -> int:
    model = load_nerf(args.nerf, device=getattr(args, "device", "auto") or "auto")
    ds = load_dataset(args.data, downscale=getattr(args, "downscale", 1) or 1)
    from tqdm import tqdm

    with tqdm(total=len(ds), unit="frame", dynamic_ncols=True) as bar:
        values = evaluate(model, ds, progress=lambda done, total: bar.update(1))
    for name, v in zip(ds.names, values):
        print(f"{name}\t{v:.3f}")
    print(f"PSNR {float(np.mean(values)):.3f} dB over {len(values)} frames")
    return 0
