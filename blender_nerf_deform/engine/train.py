"""`train` command: train a NeRF on a transforms.json dataset, write RUN_DIR/nerf.ckpt.

    python -m blender_nerf_deform.engine train --data DIR --out RUN_DIR
        [--max-seconds S] [--steps N] [--seed N] [--device auto|cpu|cuda] [--downscale K] [--resume]

Without --max-seconds or --steps it trains for 300 seconds. The checkpoint is
rewritten (atomically) every --checkpoint-every seconds and at the end, also when
interrupted with Ctrl-C; --resume continues from RUN_DIR/nerf.ckpt (the step
count and --steps are totals; --max-seconds counts this run only).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import torch

from .checkpoint import load_nerf, read_checkpoint
from .dataset import load_dataset
from .errors import EngineError
from .model import NerfConfig, NerfModel, resolve_device
from .trainer import Trainer, TrainOptions

DEFAULT_SECONDS = 300.0


def run_training(data, out_dir, max_seconds=None, steps=None, device="auto", downscale=1, resume=False,
                 checkpoint_every=120.0, progress=True, config_overrides: dict | None = None, should_stop=None,
                 seed: int = 0) -> dict:
    """Train and write out_dir/nerf.ckpt; returns a summary dict (also written to out_dir/train.json).

    `seed` seeds the initial weights as well as the trainer's sampling, so that a run of a fixed
    number of steps on the CPU repeats on the same machine (a time budget cannot: it depends on
    the machine's speed).
    """
    dev = resolve_device(device)
    if steps is not None and steps < 1:
        raise EngineError(f"--steps must be positive, got {steps}")
    if max_seconds is not None and max_seconds <= 0:
        raise EngineError(f"--max-seconds must be positive, got {max_seconds}")
    if steps is None and max_seconds is None:
        max_seconds = DEFAULT_SECONDS
    ds = load_dataset(data, downscale=downscale)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise EngineError(f"--out {out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / "nerf.ckpt"
    state = None
    if resume and ckpt.exists():
        state = read_checkpoint(ckpt).get("trainer")
        model = load_nerf(ckpt, device=dev).train()
    else:
        cfg = NerfConfig(aabb=[float(v) for v in ds.aabb.reshape(-1)])
        for k, v in (config_overrides or {}).items():
            setattr(cfg, k, v)
        torch.manual_seed(seed)
        model = NerfModel(cfg).to(dev)
    opts = TrainOptions(max_seconds=max_seconds, steps=steps, checkpoint_path=str(ckpt), checkpoint_every_s=checkpoint_every,
                        seed=seed)
    trainer = Trainer(model, ds, opts)
    if state:
        trainer.load_state_dict(state)
        trainer.elapsed = 0.0  # --max-seconds counts this run
    t0 = time.perf_counter()
    summary = trainer.train(progress=progress, should_stop=should_stop)
    summary.update({"checkpoint": str(ckpt), "device": str(dev), "wall_seconds": time.perf_counter() - t0,
                    "images": len(ds), "width": ds.width, "height": ds.height})
    (out / "train.json").write_text(json.dumps(summary, indent=1))
    return summary


def main(args) -> int:
    summary = run_training(args.data, args.out, max_seconds=args.max_seconds, steps=args.steps, device=args.device,
                           downscale=getattr(args, "downscale", 1) or 1, resume=getattr(args, "resume", False),
                           checkpoint_every=getattr(args, "checkpoint_every", 120.0) or 120.0,
                           seed=getattr(args, "seed", 0))
    print(f"trained {summary['steps']} steps in {summary['seconds']:.1f} s, last batch PSNR "
          f"{summary.get('psnr', float('nan')):.2f} dB; wrote {summary['checkpoint']}")
    return 0
