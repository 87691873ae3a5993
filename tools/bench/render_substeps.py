#!/usr/bin/env python3
"""Benchmark: PSNR and frame time of a checkpoint against the samples per render step (`substeps`).

The splits are those of tools/bench/nerf_train.py: views 0, 10, 20, ... validate, views 5, 15, 25, ...
are the held-out photos of a `--final` run (never trained on, never tuned on). Each view is rendered
at every substeps value in one process (the first render warms up), PSNR on white.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/render_substeps.py --nerf FERN.ckpt \\
        --data ../shared/datasets/fern --downscale 8 --substeps 1 2 3
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from nerf_train import evaluate, split_views  # noqa: E402  (its splits; its PSNR, frame time and samples per ray)

from blender_nerf_deform.engine.nerf.checkpoint import load_nerf  # noqa: E402
from blender_nerf_deform.engine.nerf.dataset import load_dataset  # noqa: E402
from blender_nerf_deform.engine.nerf.renderer import render_image  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--nerf", required=True, help="a checkpoint of a `nerf_train.py --final --save` run")
    ap.add_argument("--data", required=True)
    ap.add_argument("--downscale", type=int, default=1)
    ap.add_argument("--substeps", type=int, nargs="+", default=[1, 2, 3])
    args = ap.parse_args()

    model = load_nerf(args.nerf, device="cpu")
    ds = load_dataset(args.data, downscale=args.downscale)
    splits = dict(zip(("val", "held_out"), split_views(len(ds))))
    render_image(model, ds.cameras[0])  # warm-up: kernels, allocator
    for substeps in args.substeps:
        results = {split: evaluate(model, ds.subset(views), substeps=substeps) for split, views in splits.items()}
        row = {
            "substeps": substeps,
            **{f"{split}_{key}": value for split, r in results.items() for key, value in r.items()},
        }
        print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
