#!/usr/bin/env python3
"""Benchmark: render time of full frames of a trained NeRF on CPU, samples per ray, peak memory.

Renders the given dataset's frames (e.g. the lego_200 validation views: every 10th)
from a checkpoint, reports the median and max seconds per frame, the samples whose
density / colour were evaluated per ray, PSNR on white, and the process's peak RSS.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/nerf_render.py --nerf RUN/nerf.ckpt \\
        --data ../shared/datasets/lego_200 --every 10
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from blender_nerf_deform.engine.nerf.checkpoint import load_nerf  # noqa: E402
from blender_nerf_deform.engine.nerf.dataset import load_dataset  # noqa: E402
from blender_nerf_deform.engine.nerf.renderer import render_image  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--nerf", required=True)
    ap.add_argument("--data", default="../shared/datasets/lego_200")
    ap.add_argument("--every", type=int, default=10, help="render frames 0, every, 2*every, ...")
    ap.add_argument("--chunk", type=int, default=4096)
    ap.add_argument("--downscale", type=int, default=1)
    ap.add_argument(
        "--early-stop",
        type=float,
        nargs="*",
        default=[1e-4],
        help="transmittance thresholds to compare (each also the colour weight threshold; "
        "default the renderer's, 1e-4)",
    )
    ap.add_argument("--json")
    args = ap.parse_args()
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    model = load_nerf(args.nerf, device="cpu")
    ds = load_dataset(args.data, downscale=args.downscale)
    ds = ds.subset(range(0, len(ds), args.every))
    render_image(model, ds.cameras[0], chunk=args.chunk)  # warm-up: numba compilation, allocator
    rss_loaded = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    results = []
    for eps in args.early_stop:
        times, psnrs, dspr, cspr = [], [], [], []
        for cam, img in zip(ds.cameras, ds.images):
            t = time.perf_counter()
            out = render_image(
                model, cam, background=(1.0, 1.0, 1.0), chunk=args.chunk, early_stop_eps=eps, weight_threshold=eps
            )
            times.append(time.perf_counter() - t)
            gt = img[..., :3] * img[..., 3:] + (1 - img[..., 3:])
            psnrs.append(-10 * np.log10(np.mean((out["rgb"] - gt) ** 2)))
            dspr.append(out["density_samples_per_ray"])
            cspr.append(out["color_samples_per_ray"])
        results.append(
            {
                "early_stop": eps,
                "frames": len(times),
                "size": f"{ds.width}x{ds.height}",
                "chunk": args.chunk,
                "seconds_median": float(np.median(times)),
                "seconds_max": float(np.max(times)),
                "density_samples_per_ray": float(np.mean(dspr)),
                "color_samples_per_ray": float(np.mean(cspr)),
                "psnr_white": float(np.mean(psnrs)),
            }
        )
    res = {
        "results": results,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "rss_mb_before_load": rss0,
        "rss_mb_after_first_frame": rss_loaded,
        "threads": torch.get_num_threads(),
    }
    print(json.dumps(res, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
