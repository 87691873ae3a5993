#!/usr/bin/env python3
"""Benchmark: validation PSNR of NeRF training (lego_200 by default; fox, fern, a room) against training time.

Validation split: every 10th view (lego's 90: indices 0, 10, ..., 80) is held
out; the others train. With --final, the views 5, 15, 25, ... are kept out as well, from
training and from the validation marks (with --train-val the validation views train too, as a
user's `train` uses every photo it is given; the marks then score views it trained on): they
are rendered once, at the end, the figure on photos nothing was tuned on (tune on the
validation marks, report the final split), marched at the training step (`final`, comparable
with earlier figures) and as `render` and F12 march final frames (`final_substeps`:
substeps.FINAL_SUBSTEPS samples per step). PSNR is on white (photos without alpha: on the
photo itself), over all held-out views, measured at the given training times (the time spent
validating is not counted). Also reports the
render time of one 200x200 validation frame, samples per ray and peak memory (RSS).

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/nerf_train.py \\
        --data ../shared/datasets/lego_200 --seconds 600 --json /tmp/train.json
    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/nerf_train.py \
        --data ../shared/datasets/fox --downscale 4 --seconds 600 --json /tmp/fox.json
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

from blender_nerf_deform.engine.nerf import renderer  # noqa: E402
from blender_nerf_deform.engine.nerf.dataset import load_dataset  # noqa: E402
from blender_nerf_deform.engine.nerf.model import NerfModel  # noqa: E402
from blender_nerf_deform.engine.nerf.renderer import render_image  # noqa: E402
from blender_nerf_deform.engine.nerf.substeps import FINAL_SUBSTEPS  # noqa: E402
from blender_nerf_deform.engine.nerf.trainer import Trainer, TrainOptions, config_for  # noqa: E402


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def split_views(n_views: int) -> tuple[list[int], list[int]]:
    """(validation views 0, 10, 20, ...; held-out views 5, 15, 25, ... of a --final run) of a dataset."""
    return list(range(0, n_views, 10)), list(range(5, n_views, 10))


def evaluate(model, ds, substeps: int = 1, pictures: str | None = None) -> dict:
    """PSNR on white over the views of ds; with `pictures`, each view's photo and render side by side as a PNG
    in that folder (floaters are seen before they are measured)."""
    psnrs, times, spr, cspr = [], [], [], []
    for cam, img in zip(ds.cameras, ds.images):
        t = time.perf_counter()
        out = render_image(model, cam, background=(1.0, 1.0, 1.0), substeps=substeps)
        times.append(time.perf_counter() - t)
        gt = img[..., :3] * img[..., 3:] + (1.0 - img[..., 3:])
        psnrs.append(-10.0 * np.log10(np.mean((out["rgb"] - gt) ** 2)))
        spr.append(out["density_samples_per_ray"])
        cspr.append(out["color_samples_per_ray"])
        if pictures:
            from PIL import Image

            Path(pictures).mkdir(parents=True, exist_ok=True)
            pair = np.concatenate([gt, out["rgb"]], axis=1)
            Image.fromarray((np.clip(pair, 0, 1) * 255 + 0.5).astype(np.uint8)).save(
                Path(pictures) / f"{cam.name}_{psnrs[-1]:.1f}dB.png"
            )
    return {
        "psnr": float(np.mean(psnrs)),
        "render_s_median": float(np.median(times)),
        "density_samples_per_ray": float(np.mean(spr)),
        "color_samples_per_ray": float(np.mean(cspr)),
        "psnr_per_view": [round(float(p), 2) for p in psnrs],
    }


def pose_summary(trainer: Trainer) -> dict | None:
    """How far pose refinement moved the training photos: mean and largest rotation (degrees) and shift."""
    if trainer.pose_delta is None:
        return None
    with torch.no_grad():
        angle = torch.rad2deg(trainer.pose_delta[:, :3].norm(dim=-1))
        shift = trainer.pose_corrections()[1].norm(dim=-1)
    return {
        "rotation_deg_mean": float(angle.mean()),
        "rotation_deg_max": float(angle.max()),
        "shift_mean": float(shift.mean()),
        "shift_max": float(shift.max()),
        "scene_half_width": trainer.pose_scale,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/datasets/lego_200")
    ap.add_argument("--seconds", type=float, default=600)
    ap.add_argument("--at", default="60,120,300,600", help="training seconds at which to validate")
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--save", help="write the final checkpoint here")
    ap.add_argument("--log2-table", type=int, default=None)
    ap.add_argument("--finest", type=int, default=None)
    ap.add_argument("--levels", type=int, default=None, help="hash grid levels (default: NerfConfig's)")
    ap.add_argument("--features", type=int, default=None, help="features per level (default: NerfConfig's)")
    ap.add_argument(
        "--color-layers", type=int, default=None, help="hidden layers of the colour MLP (default: NerfConfig's)"
    )
    ap.add_argument("--occ-res", type=int, default=None)
    ap.add_argument("--target-samples", type=int, default=None)
    ap.add_argument("--lr", type=float, default=None, help="peak learning rate (default: TrainOptions.lr)")
    ap.add_argument("--lr-final", type=float, default=None)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--device", default="cpu", help="cpu or cuda (the torch path)")
    ap.add_argument("--downscale", type=int, default=1, help="box-filter the images by this factor (fox: 4 → 270x480)")
    ap.add_argument(
        "--scene",
        default="auto",
        choices=("auto", "bounded", "unbounded"),
        help="the trainer's scene model (auto: unbounded for photos without alpha)",
    )
    ap.add_argument("--steps-per-diagonal", type=int, default=None)
    ap.add_argument(
        "--occ-threshold", type=float, default=None, help="occupancy threshold (opacity over one render step)"
    )
    ap.add_argument(
        "--final",
        action="store_true",
        help="also keep views 5, 15, 25, ... out, evaluated only once at the end (never tune on them)",
    )
    ap.add_argument(
        "--train-val",
        action="store_true",
        help="with --final, the validation views train too: a user's training set, every photo but the "
        "held-out ones (the marks' val PSNR is then on views it trained on)",
    )
    ap.add_argument("--appearance-dim", type=int, default=0, help="per-image appearance code size (0: none)")
    ap.add_argument("--distortion", type=float, default=None, help="distortion loss weight (default: the trainer's)")
    ap.add_argument(
        "--occ-every",
        type=int,
        default=None,
        help="update the occupancy grids every this many steps (default: 16 per grid)",
    )
    ap.add_argument(
        "--train-round",
        type=int,
        default=None,
        help="samples marched per training round (default: renderer.TRAIN_SAMPLES_PER_ROUND)",
    )
    ap.add_argument(
        "--error-rays",
        type=float,
        default=None,
        help="fraction of each step's rays drawn from the error map (default: TrainOptions.error_rays)",
    )
    ap.add_argument("--near-plane", type=float, default=None, help="rays start this far from the camera (scene units)")
    ap.add_argument(
        "--train-every",
        type=int,
        default=1,
        help="train on every K-th of the training views only: a sparser capture of the same scene, "
        "validated and held out on the same views",
    )
    ap.add_argument("--pictures", help="with --final: write each held-out photo beside its final render here (PNG)")
    ap.add_argument(
        "--masks",
        default="auto",
        choices=("auto", "object", "ignore"),
        help="what the dataset's masks mean (default auto: decided by their shape)",
    )
    ap.add_argument(
        "--min-views",
        type=int,
        default=None,
        help="inner cells that some but fewer than this many training photos see (their rendered depth "
        "reaches the cell) hold no density (default: TrainOptions.min_views, off)",
    )
    ap.add_argument("--refine-poses", action="store_true", help="learn a correction of each training photo's pose")
    ap.add_argument(
        "--pose-lr", type=float, default=None, help="its peak learning rate (default: TrainOptions.pose_lr)"
    )
    ap.add_argument(
        "--pose-start",
        type=float,
        default=None,
        help="fraction of the budget before the poses move (default: TrainOptions.pose_start)",
    )
    args = ap.parse_args()
    if args.train_val and not args.final:
        ap.error("--train-val needs --final: without held-out views nothing would be left unseen")
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.train_round:
        renderer.TRAIN_SAMPLES_PER_ROUND = args.train_round

    ds = load_dataset(args.data, downscale=args.downscale, masks=args.masks)
    if ds.mask_meaning:
        print(f"masks: {ds.mask_meaning} ({ds.mask_reason})", file=sys.stderr)
    val_idx, held_out = split_views(len(ds))
    final_idx = held_out if args.final else []
    train_idx = [i for i in range(len(ds)) if i not in final_idx and (args.train_val or i not in val_idx)]
    train = ds.subset(train_idx[:: args.train_every])
    val = ds.subset(val_idx)
    cfg = config_for(ds, args.scene)
    if args.steps_per_diagonal:
        cfg.steps_per_diagonal = args.steps_per_diagonal
    if args.appearance_dim:
        cfg.appearance_dim, cfg.appearance_count = args.appearance_dim, len(train)
    if args.log2_table:
        cfg.log2_table_size = args.log2_table
    if args.finest:
        cfg.finest_resolution = args.finest
    if args.levels:
        cfg.n_levels = args.levels
    if args.features:
        cfg.n_features = args.features
    if args.color_layers is not None:  # 0 is a valid colour head (no hidden layer)
        cfg.color_layers = args.color_layers
    if args.occ_res:
        cfg.occ_resolution = args.occ_res
    if args.occ_threshold is not None:
        cfg.occ_threshold = args.occ_threshold
    if args.near_plane is not None:
        cfg.near_plane = args.near_plane
    opts = TrainOptions(max_seconds=args.seconds)
    if args.target_samples:
        opts.target_samples = args.target_samples
    if args.lr:
        opts.lr = args.lr
    if args.lr_final:
        opts.lr_final_factor = args.lr_final
    if args.distortion is not None:
        opts.distortion_weight = args.distortion
    if args.occ_every:
        opts.occ_update_every = args.occ_every
    if args.error_rays is not None:
        opts.error_rays = args.error_rays
    opts.refine_poses = args.refine_poses
    if args.min_views is not None:
        opts.min_views = args.min_views
    if args.pose_lr is not None:
        opts.pose_lr = args.pose_lr
    if args.pose_start is not None:
        opts.pose_start = args.pose_start
    torch.manual_seed(0)
    model = NerfModel(cfg).to(args.device)
    trainer = Trainer(model, train, opts)
    marks = [float(x) for x in args.at.split(",") if float(x) <= args.seconds]
    results = []
    rss_before_eval = [0.0]

    def callback(tr: Trainer) -> None:
        while marks and tr.elapsed >= marks[0]:
            mark = marks.pop(0)
            rss_before_eval[0] = peak_rss_mb()
            r = evaluate(tr.model, val)
            r.update(
                {
                    "at_s": mark,
                    "train_s": round(tr.elapsed, 1),
                    "step": tr.step_count,
                    "rays_per_step": tr.last.get("rays"),
                    "train_samples_per_ray": tr.last.get("samples_per_ray"),
                    "train_density_samples_per_ray": tr.last.get("density_samples_per_ray"),
                    "occupied_cells": int(tr.model.occupancy.mask.sum()),
                }
            )
            results.append(r)
            print(json.dumps(r), flush=True)

    t0 = time.perf_counter()
    trainer.train(progress=False, callback=callback)
    wall = time.perf_counter() - t0
    if marks:  # budget ended between marks: validate the final model at the end
        callback(trainer)
    final = final_substeps = None
    if final_idx:
        final = evaluate(trainer.model, ds.subset(final_idx))
        final.update({"views": final_idx})
        print(json.dumps({"final": final}), flush=True)
        final_substeps = evaluate(trainer.model, ds.subset(final_idx), substeps=FINAL_SUBSTEPS, pictures=args.pictures)
        final_substeps.update({"views": final_idx, "substeps": FINAL_SUBSTEPS})
        print(json.dumps({"final_substeps": final_substeps}), flush=True)
    summary = {
        "data": args.data,
        "downscale": args.downscale,
        "images": [train.width, train.height, len(train), len(val)],
        "val_trained": args.train_val,
        "config": cfg.to_dict(),
        "options": {
            k: getattr(opts, k)
            for k in ("target_samples", "lr", "lr_final_factor", "refine_poses", "pose_lr", "pose_start")
        },
        "results": results,
        "final": final,
        "final_substeps": final_substeps,
        "pose_corrections": pose_summary(trainer),
        "steps": trainer.step_count,
        "train_seconds": trainer.elapsed,
        "wall_seconds": wall,
        "peak_rss_mb_training": rss_before_eval[0],
        "peak_rss_mb_total": peak_rss_mb(),
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "device": str(model.device) + (f" ({torch.cuda.get_device_name()})" if model.device.type == "cuda" else ""),
    }
    print(json.dumps({k: v for k, v in summary.items() if k != "results"}), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=1))
    if args.save:
        from blender_nerf_deform.engine.nerf.checkpoint import save_nerf

        save_nerf(model, args.save)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
