#!/usr/bin/env python3
"""Benchmark: kernel launches and host-device syncs of the CUDA code path, counted on the CPU.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/cuda_launches.py --json /tmp/launches.json

Trains lego_200 (the held-out tenth left out) on the CPU kernels for --warm-steps, then runs
--count-steps training steps on the CUDA code path (`backend.forced("torch")`, with Triton kernels
under its interpreter when TRITON_INTERPRET=1) inside a `LaunchCounter`, and renders a --size frame of
the first camera at rest and through a twisted box cage. Prints launches and syncs per training step,
per frame, per megapixel and per render round (a round: one march of the live rays, see renderer.py).
On a machine with CUDA, --device cuda counts the same on the GPU.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))


def twisted(rest, aabb, turns=0.15):
    """The box cage's vertices twisted about the box's vertical (z) axis, more towards the top."""
    import numpy as np

    lo, hi = np.asarray(aabb[:3]), np.asarray(aabb[3:])
    c = 0.5 * (lo + hi)
    h = (rest[:, 2] - lo[2]) / (hi[2] - lo[2])
    a = 2 * np.pi * turns * h
    x, y = rest[:, 0] - c[0], rest[:, 1] - c[1]
    out = rest.copy()
    out[:, 0] = c[0] + np.cos(a) * x - np.sin(a) * y
    out[:, 1] = c[1] + np.sin(a) * x + np.cos(a) * y
    return out


def count_rounds():
    """Counts the render rounds (calls of march_kernels.march_round, or of march_round_device on the device
    path: one march of the live rays each) while the bench runs."""
    from blender_nerf_deform.engine.nerf import march_kernels

    calls = {"n": 0}
    for name in ("march_round", "march_round_device"):
        original = getattr(march_kernels, name, None)
        if original is None:
            continue

        def counted(*args, _original=original, **kwargs):
            calls["n"] += 1
            return _original(*args, **kwargs)

        setattr(march_kernels, name, counted)
    return calls


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/datasets/lego_200")
    ap.add_argument("--warm-steps", type=int, default=300, help="steps on the CPU kernels before counting")
    ap.add_argument("--count-steps", type=int, default=32, help="steps counted (two occupancy updates)")
    ap.add_argument("--size", type=int, default=100, help="frame width and height")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json")
    args = ap.parse_args()
    import numpy as np
    import torch

    from blender_nerf_deform.engine import backend
    from blender_nerf_deform.engine.bend.cage_bend import CageBend
    from blender_nerf_deform.engine.geometry.cage import box_cage
    from blender_nerf_deform.engine.launch_count import LaunchCounter
    from blender_nerf_deform.engine.nerf.camera import Camera
    from blender_nerf_deform.engine.nerf.dataset import load_dataset
    from blender_nerf_deform.engine.nerf.model import NerfConfig, NerfModel
    from blender_nerf_deform.engine.nerf.renderer import render_image
    from blender_nerf_deform.engine.nerf.trainer import Trainer, TrainOptions

    ds = load_dataset(args.data)
    train = ds.subset([i for i in range(len(ds)) if i % 10])
    torch.manual_seed(0)
    model = NerfModel(NerfConfig(aabb=ds.aabb.reshape(-1).tolist()))
    t0 = time.perf_counter()
    warm = Trainer(model, train, TrainOptions(steps=args.warm_steps + args.count_steps))
    for _ in range(args.warm_steps):
        warm.step()
    warm.model.encoding.fused_grad = False
    warm_s = time.perf_counter() - t0
    model = model.to(args.device)
    out = {"data": args.data, "warm_steps": args.warm_steps, "device": args.device, "warm_seconds": round(warm_s, 1)}
    with backend.forced("torch"):
        out["triton"] = backend.use_triton(args.device) if hasattr(backend, "use_triton") else False
        trainer = Trainer(model, train, TrainOptions(steps=args.warm_steps + args.count_steps))
        trainer.load_state_dict(warm.state_dict())
        steps = []
        for _ in range(args.count_steps):
            with LaunchCounter() as c:
                info = trainer.step()
            steps.append(
                {
                    "launches": c.launches,
                    "syncs": c.syncs,
                    "rays": info["rays"],
                    "samples_per_ray": round(info["samples_per_ray"], 1),
                    "density_samples_per_ray": round(info.get("density_samples_per_ray", 0.0), 1),
                    "top": c.summary(8)["top_launches"],
                    "syncs_by_op": dict(c.syncs_by_op),
                }
            )
        launches = [s["launches"] for s in steps]
        syncs = [s["syncs"] for s in steps]
        out["train"] = {
            "steps": len(steps),
            "launches_mean": round(float(np.mean(launches)), 1),
            "launches_max": max(launches),
            "launches_median": float(np.median(launches)),
            "syncs_mean": round(float(np.mean(syncs)), 2),
            "syncs_max": max(syncs),
            "rays_mean": round(float(np.mean([s["rays"] for s in steps])), 1),
            "a_step": steps[-1],
        }
        model.eval()
        c2w = np.asarray(ds.cameras[0].c2w, dtype=np.float64)
        cam0 = ds.cameras[0]
        camera = Camera(
            fx=cam0.fx * args.size / cam0.width,
            fy=cam0.fy * args.size / cam0.height,
            cx=cam0.cx * args.size / cam0.width,
            cy=cam0.cy * args.size / cam0.height,
            width=args.size,
            height=args.size,
            c2w=c2w,
        )
        rest, tets = box_cage((4, 4, 4), lo=model.config.aabb[:3], hi=model.config.aabb[3:])
        bend = CageBend(model, rest, tets).set_deformed(twisted(rest, model.config.aabb))
        rounds = count_rounds()
        megapixels = args.size * args.size / 1e6
        for name, kwargs in (("rest", {}), ("bent", bend.render_kwargs())):
            rounds["n"] = 0
            t = time.perf_counter()
            with LaunchCounter() as c:
                frame = render_image(model, camera, **kwargs)
            seconds = time.perf_counter() - t
            n_rounds = max(rounds["n"], 1)
            out[name] = {
                "launches": c.launches,
                "syncs": c.syncs,
                "rounds": rounds["n"],
                "launches_per_megapixel": round(c.launches / megapixels),
                "syncs_per_round": round(c.syncs / n_rounds, 2),
                "launches_per_round": round(c.launches / n_rounds, 1),
                "seconds_cpu": round(seconds, 2),
                "samples_per_ray": [
                    round(float(frame.get("density_samples_per_ray", 0)), 2),
                    round(float(frame.get("color_samples_per_ray", 0)), 2),
                ],
                "top": c.summary(10)["top_launches"],
                "syncs_by_op": dict(c.syncs_by_op),
            }
    text = json.dumps(out, indent=1)
    print(text)
    if args.json:
        Path(args.json).write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
