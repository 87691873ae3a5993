#!/usr/bin/env python3
"""Benchmark: this checkout's hash-encoding kernels against another checkout's, in one process.

Trains --warm steps on --data from scratch, or from --nerf (a checkpoint trained on --data: the
late-training batch, at the late learning rate), views 0, 5, 10, ... left out as
tools/bench/nerf_train.py --final does; then, alternating the two kernel sets
(`encoding_kernels._hash_forward` / `_hash_backward` of each checkout, everything else this
checkout's):

- the kernels alone on the samples of one training step that updates no occupancy grid (forward
  over the step's density samples, backward over its gradient samples), --repeats rounds, min and
  median;
- whole training steps, --repeats blocks of --steps steps each (the model keeps training, so
  compare the blocks pairwise: both kernel sets see the same stage of training);
- with --frame, the first held-out view (5) rendered at the trainer's state (`render_image`, 2
  substeps, as `render` and F12 march), 6 times each.

Both kernel sets must give the same numbers (checked on the step's samples before timing).

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/hash_kernels.py --old-tree ../old-checkout \\
        --data ../shared/datasets/fern --downscale 8 --warm 800
    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/hash_kernels.py --old-tree ../old-checkout \\
        --data ../shared/datasets/fox --downscale 4 --nerf FOX600.ckpt --warm 20 --frame
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from blender_nerf_deform.engine.nerf import encoding_kernels  # noqa: E402
from blender_nerf_deform.engine.nerf.checkpoint import load_nerf  # noqa: E402
from blender_nerf_deform.engine.nerf.dataset import load_dataset  # noqa: E402
from blender_nerf_deform.engine.nerf.model import NerfModel  # noqa: E402
from blender_nerf_deform.engine.nerf.renderer import render_image  # noqa: E402
from blender_nerf_deform.engine.nerf.trainer import OCC_UPDATE_EVERY_PER_GRID, Trainer, TrainOptions, config_for  # noqa: E402

MODULE = Path("blender_nerf_deform/engine/nerf/encoding_kernels.py")


def other_kernels(tree: Path):
    """(forward, backward) of the other checkout's encoding_kernels.py, imported beside this one's."""
    path = (tree / MODULE).resolve()
    if not path.is_file():
        raise SystemExit(f"error: {path} does not exist: --old-tree must be a checkout of this repository")
    spec = importlib.util.spec_from_file_location("blender_nerf_deform.engine.nerf._other_encoding_kernels", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module._hash_forward, module._hash_backward


def use(kernels) -> None:
    encoding_kernels._hash_forward, encoding_kernels._hash_backward = kernels


def one_step_samples(trainer: Trainer) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A training step's density samples (normalised), and its gradient samples with their output gradient."""
    seen = {"forward": [], "backward": []}
    fwd, bwd = encoding_kernels._hash_forward, encoding_kernels._hash_backward

    def forward(x, *args):
        seen["forward"].append(x.copy())
        return fwd(x, *args)

    def backward(x, g, *args):
        seen["backward"].append((x.copy(), g.copy()))
        return bwd(x, g, *args)

    every = trainer.opt.occ_update_every or OCC_UPDATE_EVERY_PER_GRID * len(trainer.grids)
    while trainer.step_count % every == 0:  # the captured step updates no grid
        trainer.step()
    use((forward, backward))
    try:
        trainer.step()
    finally:
        use((fwd, bwd))
    density = np.concatenate(seen["forward"])
    x, g = seen["backward"][0]
    return density, x, g


def seconds(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def summary(name: str, times: list[float], unit: float = 1e3) -> str:
    return f"{name} min {min(times) * unit:.2f} median {statistics.median(times) * unit:.2f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--old-tree", required=True, type=Path, help="the checkout whose kernels to compare with")
    ap.add_argument("--data", default="../shared/datasets/fern")
    ap.add_argument("--downscale", type=int, default=8)
    ap.add_argument("--nerf", help="start from this checkpoint (trained on --data) instead of from scratch")
    ap.add_argument("--warm", type=int, default=800, help="training steps before timing")
    ap.add_argument("--steps", type=int, default=20, help="training steps per timed block")
    ap.add_argument("--repeats", type=int, default=12, help="timed blocks (rounds of kernel calls) per kernel set")
    ap.add_argument("--frame", action="store_true", help="also time a held-out frame (2 substeps) with each set")
    args = ap.parse_args()

    kernels = {
        "old": other_kernels(args.old_tree),
        "new": (encoding_kernels._hash_forward, encoding_kernels._hash_backward),
    }
    ds = load_dataset(args.data, downscale=args.downscale)
    held_out = list(range(5, len(ds), 10))
    torch.manual_seed(0)
    model = load_nerf(args.nerf, device="cpu") if args.nerf else NerfModel(config_for(ds))
    trainer = Trainer(model, ds.subset([i for i in range(len(ds)) if i % 5]), TrainOptions(max_seconds=600))
    if args.nerf:
        trainer.step_count, trainer.elapsed = 5000, 590.0  # past the warm-ups, at the late learning rate
    for _ in range(args.warm):
        trainer.step()

    enc = trainer.model.encoding
    arrs = enc._kernel_arrays
    table = enc.table.detach().numpy()
    density, x, g = one_step_samples(trainer)
    print(
        f"after {trainer.step_count} steps: {len(density)} density samples, {len(x)} gradient samples in a step; "
        f"{trainer.last['rays']} rays",
        flush=True,
    )
    outs, grads = {}, {}
    for name, (fwd, bwd) in kernels.items():
        outs[name] = np.empty((len(density), enc.out_dim), np.float32)
        grads[name] = (np.zeros_like(table), np.zeros(table.shape[0], np.uint8))
        fwd(density, table, arrs.res, arrs.dense, arrs.size, arrs.off, outs[name])
        bwd(x, g, arrs.res, arrs.dense, arrs.size, arrs.off, *grads[name])
    same = (
        np.array_equal(outs["old"], outs["new"])
        and np.array_equal(grads["old"][0], grads["new"][0])
        and np.array_equal(grads["old"][1], grads["new"][1])
    )
    print("same values:", same, flush=True)

    times = {f"{name} {part}": [] for name in kernels for part in ("forward", "backward", "step")}
    for r in range(args.repeats):
        for name in ("old", "new") if r % 2 == 0 else ("new", "old"):
            fwd, bwd = kernels[name]
            times[f"{name} forward"].append(
                seconds(
                    lambda fwd=fwd, name=name: fwd(
                        density, table, arrs.res, arrs.dense, arrs.size, arrs.off, outs[name]
                    )
                )
            )
            times[f"{name} backward"].append(
                seconds(lambda bwd=bwd, name=name: bwd(x, g, arrs.res, arrs.dense, arrs.size, arrs.off, *grads[name]))
            )
    for r in range(args.repeats):
        for name in ("old", "new") if r % 2 == 0 else ("new", "old"):
            use(kernels[name])
            t = time.perf_counter()
            for _ in range(args.steps):
                trainer.step()
            times[f"{name} step"].append((time.perf_counter() - t) / args.steps)
    use(kernels["new"])
    for key, values in times.items():
        print(summary(key + " ms", values), flush=True)
    pairs = [n / o for o, n in zip(times["old step"], times["new step"])]
    print(
        f"step new/old, pairwise: median {statistics.median(pairs):.3f} "
        f"(range {min(pairs):.3f}-{max(pairs):.3f}); now {trainer.last['rays']} rays a step",
        flush=True,
    )
    if args.frame and held_out:
        camera = ds.cameras[held_out[0]]
        trainer.model.eval()
        frame = {"old": [], "new": []}
        for r in range(6):
            for name in ("old", "new") if r % 2 == 0 else ("new", "old"):
                use(kernels[name])
                frame[name].append(seconds(lambda: render_image(trainer.model, camera, substeps=2)))
        use(kernels["new"])
        for name, values in frame.items():
            print(summary(f"{name} frame {camera.width}x{camera.height} s", values, unit=1.0), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
