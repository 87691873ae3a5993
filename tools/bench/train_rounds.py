#!/usr/bin/env python3
"""Benchmark: a late training step's time against the trainer's round size (renderer.TRAIN_SAMPLES_PER_ROUND).

A training ray is marched in rounds; it ends inside its last round, so a smaller round evaluates
fewer densities past the surface but pays more rounds. Resumes from a trained checkpoint (the
late-training batch: few samples per ray, many rays), views 0, 5, 10, 15, ... left out as
tools/bench/nerf_train.py --final does, and alternates the round sizes in one process:

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/train_rounds.py --nerf FERN600.ckpt \\
        --data ../shared/datasets/fern --downscale 8 --rounds 65536 32768 16384 8192
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from blender_nerf_deform.engine.nerf import renderer  # noqa: E402
from blender_nerf_deform.engine.nerf.checkpoint import load_nerf  # noqa: E402
from blender_nerf_deform.engine.nerf.dataset import load_dataset  # noqa: E402
from blender_nerf_deform.engine.nerf.trainer import Trainer, TrainOptions  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--nerf", required=True, help="a checkpoint trained on --data (e.g. nerf_train.py --save)")
    ap.add_argument("--data", required=True)
    ap.add_argument("--downscale", type=int, default=1)
    ap.add_argument("--rounds", type=int, nargs="+", default=[1 << 16, 1 << 14])
    ap.add_argument("--steps", type=int, default=25, help="steps per timed block")
    ap.add_argument("--repeats", type=int, default=4, help="timed blocks per round size, alternating")
    args = ap.parse_args()
    ds = load_dataset(args.data, downscale=args.downscale)
    train = ds.subset([i for i in range(len(ds)) if i % 5])
    torch.manual_seed(0)
    trainer = Trainer(load_nerf(args.nerf, device="cpu"), train, TrainOptions(max_seconds=600))
    trainer.step_count, trainer.elapsed = 5000, 590.0  # past the warm-ups, at the late learning rate
    for _ in range(20):  # the dynamic batch settles
        trainer.step()
    ms = {r: [] for r in args.rounds}
    density = {r: [] for r in args.rounds}
    for rep in range(args.repeats):
        for r in args.rounds if rep % 2 == 0 else args.rounds[::-1]:
            renderer.TRAIN_SAMPLES_PER_ROUND = r
            t = time.perf_counter()
            for _ in range(args.steps):
                density[r].append(trainer.step()["density_samples_per_ray"])
            ms[r].append(1000 * (time.perf_counter() - t) / args.steps)
    for r in args.rounds:
        print(
            f"round {r:6d}: {np.median(ms[r]):6.1f} ms a step (min {min(ms[r]):.1f}, max {max(ms[r]):.1f}); "
            f"{np.mean(density[r]):.1f} density samples per ray; {trainer.last['rays']} rays a step"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
