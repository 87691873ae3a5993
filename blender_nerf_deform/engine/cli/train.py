"""`train`: train a NeRF on a transforms.json dataset, write RUN_DIR/nerf.ckpt.

    python -m blender_nerf_deform.engine train --data DIR --out RUN_DIR
        [--max-seconds S] [--steps N] [--seed N] [--device auto|cpu|cuda] [--downscale K]
        [--scene auto|bounded|unbounded]
        [--masks auto|object|ignore] [--resume | --overwrite]

Without --max-seconds or --steps it trains for 300 seconds. The checkpoint is
rewritten (atomically) every --checkpoint-every seconds and at the end, also when
interrupted with Ctrl-C; --resume continues from RUN_DIR/nerf.ckpt (the step
count and --steps are totals; --max-seconds counts this run only); --overwrite replaces it
(without either, an existing checkpoint is an error). One train process at a time per RUN_DIR.
"""

from __future__ import annotations

from ..nerf.trainer import run_training


def main(args) -> int:
    summary = run_training(
        args.data,
        args.out,
        max_seconds=args.max_seconds,
        steps=args.steps,
        device=args.device,
        downscale=getattr(args, "downscale", 1),
        resume=getattr(args, "resume", False),
        checkpoint_every=getattr(args, "checkpoint_every", 120.0),
        seed=getattr(args, "seed", 0),
        overwrite=getattr(args, "overwrite", False),
        scene_model=getattr(args, "scene", "auto"),
        drop_blurry=getattr(args, "drop_blurry", 0.0),
        masks=getattr(args, "masks", "auto"),
    )
    print(
        f"trained {summary['steps']} steps in {summary['seconds']:.1f} s, last batch PSNR "
        f"{summary.get('psnr', float('nan')):.2f} dB; wrote {summary['checkpoint']}"
    )
    return 0
