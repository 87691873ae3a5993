#!/usr/bin/env python3
"""Benchmark: seconds for N training steps on lego_200, for A/B runs of two code trees in the same session.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/train_steps.py --tree /path/to/old/checkout --steps 600
    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/train_steps.py --tree . --steps 600

Alternate the trees (old, new, old, new): this machine's speed drifts by tens of per cent
between minutes, so only pairs run one after the other compare.
"""

from __future__ import annotations

import argparse
import sys
import time


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tree", default=".", help="repository checkout whose engine to time")
    ap.add_argument("--data", default="../shared/datasets/lego_200")
    ap.add_argument("--steps", type=int, default=600)
    args = ap.parse_args()
    sys.path.insert(0, args.tree)
    import torch

    from blender_nerf_deform.engine.nerf.dataset import load_dataset
    from blender_nerf_deform.engine.nerf.model import NerfConfig, NerfModel
    from blender_nerf_deform.engine.nerf.trainer import Trainer, TrainOptions

    ds = load_dataset(args.data)
    train = ds.subset([i for i in range(len(ds)) if i % 10])
    torch.manual_seed(0)
    trainer = Trainer(NerfModel(NerfConfig(aabb=ds.aabb.reshape(-1).tolist())), train, TrainOptions(steps=args.steps))
    t = time.perf_counter()
    marks = {}
    for i in range(args.steps):
        info = trainer.step()
        if (i + 1) in (100, 300, args.steps):
            marks[i + 1] = round(time.perf_counter() - t, 2)
    print(args.tree, "seconds at steps", marks, "last batch", {k: round(v, 2) for k, v in info.items()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
