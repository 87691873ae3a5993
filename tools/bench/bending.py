#!/usr/bin/env python3
"""Benchmark: render time of a ray-bent frame over the undeformed frame (issue 5 target <= 1.25).

Same checkpoint, same cameras, same process: each camera is rendered
undeformed and ray-bent (in alternating order, `--reps` times each, median
kept), at the dataset's resolution (200x200 for lego_200), on the CPU. The
deformation is a smooth twist of the object's upper part about the vertical
axis through the cage's centre: 0 below `--from` and rising smoothly
(smoothstep in z) to `--degrees` at the cage's top.

Reported: seconds per frame undeformed / bent (the bend already posed),
their ratio, the per-frame cost of posing the cage (`CageBend.set_deformed`:
deformed locator + deformed occupancy) and the ratio with it included;
samples per ray; PSNR of the undeformed frames against the dataset's images
(white background) and of identity-bent frames against undeformed ones (the
bending path itself, should be >= 50 dB).

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/bending.py --nerf RUN/nerf.ckpt \\
        --cage RUN/cage.npz --data ../shared/datasets/lego_200 --every 10
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from blender_nerf_deform.engine.bend.cage_bend import CageBend  # noqa: E402
from blender_nerf_deform.engine.geometry.mesh_io import load_cage  # noqa: E402
from blender_nerf_deform.engine.nerf.checkpoint import load_nerf  # noqa: E402
from blender_nerf_deform.engine.nerf.dataset import load_dataset  # noqa: E402
from blender_nerf_deform.engine.nerf.renderer import render_image  # noqa: E402


def twist_upper_part(vertices: np.ndarray, degrees: float, start: float) -> np.ndarray:
    """Twist about the vertical (z) axis through the centre of the vertices' box; the angle is 0 for
    z below `start` (a fraction of the height) and rises by smoothstep to `degrees` at the top."""
    lo, hi = vertices.min(0), vertices.max(0)
    centre = 0.5 * (lo + hi)
    z0 = lo[2] + start * (hi[2] - lo[2])
    s = np.clip((vertices[:, 2] - z0) / max(hi[2] - z0, 1e-9), 0.0, 1.0)
    angle = np.radians(degrees) * s * s * (3 - 2 * s)
    c, si = np.cos(angle), np.sin(angle)
    x, y = vertices[:, 0] - centre[0], vertices[:, 1] - centre[1]
    out = vertices.copy()
    out[:, 0] = centre[0] + c * x - si * y
    out[:, 1] = centre[1] + si * x + c * y
    return out


def psnr(a, b) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else -10 * np.log10(mse)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--nerf", required=True)
    ap.add_argument("--cage", required=True, help="cage .npz written by the `cage` command for this NeRF")
    ap.add_argument("--data", default="../shared/datasets/lego_200")
    ap.add_argument("--every", type=int, default=10, help="cameras 0, every, 2*every, ...")
    ap.add_argument("--reps", type=int, default=3, help="renders per camera and mode; the median is kept")
    ap.add_argument("--degrees", type=float, default=30.0)
    ap.add_argument("--from", dest="start", type=float, default=0.5, help="twist starts at this fraction of the height")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--save", help="folder for the undeformed / bent PNGs of each camera")
    ap.add_argument("--json")
    args = ap.parse_args()

    model = load_nerf(args.nerf, device=args.device)
    ds = load_dataset(args.data)
    ds = ds.subset(range(0, len(ds), args.every))
    cage = load_cage(args.cage)
    rest, tets = cage["vertices"], cage["tets"]
    deformed = twist_upper_part(rest, args.degrees, args.start)
    t = time.perf_counter()
    bend = CageBend(model, rest, tets)
    build_s = time.perf_counter() - t
    sync = torch.cuda.synchronize if model.device.type == "cuda" else (lambda: None)

    def timed(fn):
        sync()
        t0 = time.perf_counter()
        out = fn()
        sync()
        return out, time.perf_counter() - t0

    # Identity pose first: the bending path's own error, and warm-up (numba compilation) of both paths.
    bend.set_deformed(rest)
    identity = [
        render_image(model, cam, sample_transform=bend.sample_transform, occupancy=bend.occupancy)["rgba"]
        for cam in ds.cameras
    ]
    _, pose_s = timed(lambda: bend.set_deformed(deformed))
    pose_times = [pose_s]
    for _ in range(4):
        pose_times.append(timed(lambda: bend.set_deformed(deformed))[1])
    bent_kw = {"sample_transform": bend.sample_transform, "occupancy": bend.occupancy}
    render_image(model, ds.cameras[0], **bent_kw)

    plain_s, bent_s, psnr_gt, psnr_identity, spr = [], [], [], [], {"plain": [], "bent": []}
    for k, (cam, img) in enumerate(zip(ds.cameras, ds.images)):
        tp, tb = [], []
        for rep in range(args.reps):
            order = ("plain", "bent") if (rep + k) % 2 == 0 else ("bent", "plain")
            for mode in order:
                kw = bent_kw if mode == "bent" else {}
                out, s = timed(lambda cam=cam, kw=kw: render_image(model, cam, background=(1.0, 1.0, 1.0), **kw))
                (tb if mode == "bent" else tp).append(s)
                if rep == 0:
                    spr[mode].append(out["density_samples_per_ray"])
                    if mode == "plain":
                        plain = out
                    else:
                        bent = out
        plain_s.append(float(np.median(tp)))
        bent_s.append(float(np.median(tb)))
        gt = img[..., :3] * img[..., 3:] + (1 - img[..., 3:])
        psnr_gt.append(psnr(plain["rgb"], gt))
        psnr_identity.append(psnr(identity[k], plain["rgba"]))
        if args.save:
            from blender_nerf_deform.engine.cli.render import write_png_rgba

            folder = Path(args.save)
            folder.mkdir(parents=True, exist_ok=True)
            write_png_rgba(folder / f"{cam.name}_plain.png", plain["rgba"])
            write_png_rgba(folder / f"{cam.name}_bent.png", bent["rgba"])

    plain_med, bent_med, pose_med = float(np.median(plain_s)), float(np.median(bent_s)), float(np.median(pose_times))
    res = {
        "frames": len(ds.cameras),
        "size": f"{ds.width}x{ds.height}",
        "device": str(model.device),
        "threads": torch.get_num_threads(),
        "tets": int(len(tets)),
        "cage_vertices": int(len(rest)),
        "twist_degrees": args.degrees,
        "twist_from": args.start,
        "inverted_tets": bend.inversion.n_inverted,
        "degenerate_tets": bend.inversion.n_degenerate,
        "seconds_plain_median": plain_med,
        "seconds_bent_median": bent_med,
        "ratio_bent_over_plain": bent_med / plain_med,
        "ratio_per_camera_max": float(np.max(np.array(bent_s) / np.array(plain_s))),
        "seconds_pose_median": pose_med,
        "ratio_with_pose": (bent_med + pose_med) / plain_med,
        "seconds_bend_build_once": build_s,
        "density_samples_per_ray_plain": float(np.mean(spr["plain"])),
        "density_samples_per_ray_bent": float(np.mean(spr["bent"])),
        "psnr_plain_vs_dataset_white": float(np.mean(psnr_gt)),
        "psnr_identity_bent_vs_plain_min": float(np.min(psnr_identity)),
    }
    print(json.dumps(res, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
