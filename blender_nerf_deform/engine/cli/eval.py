"""`eval`: PSNR of a checkpoint over a dataset's frames (composited on white).

    python -m blender_nerf_deform.engine eval --nerf CKPT --data DIR [--downscale K] [--substeps S] [--device D]

Prints one line per frame and a last line `PSNR <mean> dB over <n> frames`.
"""

from __future__ import annotations

from ..nerf.checkpoint import load_nerf
from ..nerf.dataset import load_dataset
from ..nerf.evaluate import evaluate


def main(args) -> int:
    model = load_nerf(args.nerf, device=args.device or "auto")
    ds = load_dataset(args.data, downscale=args.downscale)
    import sys

    print(f"read {ds.describe()}", file=sys.stderr)
    from tqdm import tqdm

    with tqdm(total=len(ds), unit="frame", dynamic_ncols=True) as bar:
        values = evaluate(model, ds, progress=lambda done, total: bar.update(1), substeps=args.substeps)
    for name, v in zip(ds.names, values):
        print(f"{name}\t{v:.3f}")
    print(f"PSNR {sum(values) / len(values):.3f} dB over {len(values)} frames")
    return 0
