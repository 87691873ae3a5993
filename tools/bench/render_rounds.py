#!/usr/bin/env python3
"""Benchmark: frame time against the renderer's round size (samples marched per round), same process, alternating.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/render_rounds.py --nerf /work/runs/fox600.ckpt \\
        --data ../shared/datasets/fox --downscale 4 --rounds 65536 16384 8192
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from blender_nerf_deform.engine.nerf import renderer  # noqa: E402
from blender_nerf_deform.engine.nerf.checkpoint import load_nerf  # noqa: E402
from blender_nerf_deform.engine.nerf.dataset import load_dataset  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--nerf", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--downscale", type=int, default=1)
    ap.add_argument("--every", type=int, default=10)
    ap.add_argument("--rounds", type=int, nargs="+", default=[1 << 16, 1 << 14])
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    model = load_nerf(args.nerf, device="cpu")
    ds = load_dataset(args.data, downscale=args.downscale)
    ds = ds.subset(range(0, len(ds), args.every))
    renderer.render_image(model, ds.cameras[0])  # warm-up
    times = {r: [] for r in args.rounds}
    stats = {}
    for _ in range(args.repeats):
        for r in args.rounds:
            renderer.RENDER_SAMPLES_PER_ROUND = r
            psnrs, spr = [], []
            for cam, img in zip(ds.cameras, ds.images):
                t = time.perf_counter()
                out = renderer.render_image(model, cam, background=(1.0, 1.0, 1.0))
                times[r].append(time.perf_counter() - t)
                gt = img[..., :3] * img[..., 3:] + (1 - img[..., 3:])
                psnrs.append(-10 * np.log10(np.mean((out["rgb"] - gt) ** 2)))
                spr.append(out["density_samples_per_ray"])
            stats[r] = {"psnr": float(np.mean(psnrs)), "density_samples_per_ray": float(np.mean(spr))}
    for r in args.rounds:
        print(json.dumps({"samples_per_round": r, "seconds_median": float(np.median(times[r])), **stats[r]}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
