#!/usr/bin/env python3
"""Inverted cage tets, the handles' surface residual and solve time per frame of `make demo`'s
animation: ARAP with the handles pinned to cage vertices (how poses were solved before issue 30) vs
the add-on's surface ARAP (engine/geometry/surface_arap.py: the handles pull the surface, no tet can
invert), on the demo's own cage, regions and handle poses.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/arap_injectivity.py [--demo demo_out]
        [--poses POSES.npz] [--save-poses POSES.npz] [--repeat 3]

The poses come from demo.blend as a render reads them: the bpy module opens it with the demo's
private Blender user folder (the extension enabled, as `tools/demo.py`'s render stage starts), and
for every frame the add-on's own `handle_pose` (addon/deform/poses.py) gives the handles' transforms (NeRF
frame) and the shared content (cage, embedding, regions) a render request carries. `--save-poses`
keeps them in an .npz, and `--poses` reads one instead of the .blend (no bpy needed).

Each frame is then solved as the worker's render op solves it (`handle_pose.RegionDeformer` built
from the same arrays, `solve(transforms)`), and by `deform.ArapDeformer` with the regions mapped to
cage vertices as hard constraints (`regions_to_cage`; the pinned region and the cut's cage vertices
pinned). Inverted tets are counted as the renderer counts them (`barycentric.inversion_report`,
det F < -1e-6); the surface residual is the largest distance of a handle's surface vertex from its
handle's affine, over the region's size. Times are the median of --repeat solves per frame, after one
warm-up solve (numba kernels compiled, the factorizations made).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

EXTENSION_MODULE = "bl_ext.user_default.blender_nerf_deform"


def poses_from_blend(demo: Path) -> dict:
    """Cage, embedding, regions and every frame's handle transforms from demo.blend (bpy module)."""
    import importlib

    os.environ["BLENDER_USER_RESOURCES"] = str(demo / "blender_user")
    import bpy

    bpy.ops.wm.read_userpref()
    if not hasattr(bpy.types.Object, "nerf_deform"):
        raise SystemExit(f"the extension is not enabled in {demo / 'blender_user'}: run `make demo` first")
    bpy.ops.wm.open_mainfile(filepath=str(demo / "demo.blend"))
    deformation = importlib.import_module(f"{EXTENSION_MODULE}.addon.deform.poses")
    scene = bpy.context.scene
    nerfs = [o for o in scene.objects if o.nerf_deform.role == "NERF"]
    if len(nerfs) != 1:
        raise SystemExit(f"expected one NeRF object in demo.blend, found {len(nerfs)}")
    out, transforms = {}, []
    for frame in range(scene.frame_start, scene.frame_end + 1):
        scene.frame_set(frame)
        pose, shared = deformation.handle_pose(nerfs[0], bpy.context.evaluated_depsgraph_get())
        transforms.append(np.asarray(pose.transforms, dtype=np.float64))
        if not out:
            out = {"mode": np.array(str(pose.mode))}
            for name in ("cage", "embedding", "regions"):
                for k, v in shared[name][1]().items():
                    out[f"{name}.{k}"] = np.asarray(v)
    out["transforms"] = np.stack(transforms)
    out["frames"] = np.arange(scene.frame_start, scene.frame_end + 1)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--demo", type=Path, default=REPO / "demo_out", help="make demo's output folder (default demo_out/)"
    )
    ap.add_argument("--poses", type=Path, help="an .npz written by --save-poses (instead of demo.blend)")
    ap.add_argument("--save-poses", type=Path, help="write the poses read from demo.blend to this .npz")
    ap.add_argument("--repeat", type=int, default=3, help="timed solves per frame and variant (median)")
    args = ap.parse_args()

    data = dict(np.load(args.poses)) if args.poses else poses_from_blend(args.demo.resolve())
    if args.save_poses:
        np.savez_compressed(args.save_poses, **data)

    from geometry_common import machine

    from blender_nerf_deform.engine.geometry.barycentric import inversion_report
    from blender_nerf_deform.engine.geometry.deform import ArapDeformer, apply_affine, regions_to_cage, split_regions
    from blender_nerf_deform.engine.geometry.embedding import Embedding
    from blender_nerf_deform.engine.geometry.handle_pose import RegionDeformer

    V, T = data["cage.vertices"].astype(np.float64), data["cage.tets"].astype(np.int64)
    tet_ids = data["embedding.tet_ids"]
    embedding = Embedding(tet_ids=tet_ids, corners=T[tet_ids], weights=data["embedding.weights"], n_outside=0)
    regions = split_regions(data["regions.handle_index"], data["regions.handle_counts"])
    pins, cut = data["regions.pin_index"], data.get("regions.cage_pin_index")
    print(
        f"machine: {machine()}; cage {len(V)} vertices, {len(T)} tets; {len(regions)} handles "
        f"({', '.join(str(len(r)) for r in regions)} surface vertices), {len(data['transforms'])} frames",
        flush=True,
    )

    surface_rest = embedding.apply(V)
    sizes = [float(np.linalg.norm(np.ptp(surface_rest[r], axis=0))) for r in regions]

    def residual(U, transforms):
        S = embedding.apply(U)
        return max(
            float(np.linalg.norm(S[r] - apply_affine(surface_rest[r], A), axis=1).max()) / size
            for r, A, size in zip(regions, transforms, sizes)
        )

    # Before: the regions' cage vertices pinned to their targets (a handle's region wins over the cut).
    cage_regions = regions_to_cage(embedding, list(regions) + ([pins] if len(pins) else []), len(V))
    fixed = cage_regions[len(regions) :]
    if cut is not None and len(cut):
        cut = np.setdiff1d(cut, np.concatenate(cage_regions[: len(regions)]))
        fixed = [np.union1d(fixed[0], cut)] if fixed else [cut]
    hard = ArapDeformer(V, T, cage_regions[: len(regions)], fixed)
    surface = RegionDeformer(V, T, embedding, regions, pins, mode="ARAP", cage_pins=data.get("regions.cage_pin_index"))
    last = list(data["transforms"][-1])
    hard.solve(last)  # warm-up: kernels, factorizations
    surface.solve(last)
    rows = []
    for frame, transforms in zip(data["frames"], data["transforms"]):
        tr = list(transforms)
        times = {"hard": [], "surface": []}
        for _ in range(max(1, args.repeat)):
            t0 = time.perf_counter()
            a = hard.solve(tr).vertices
            times["hard"].append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            b, stats = surface.solve(tr)
            times["surface"].append(time.perf_counter() - t0)
        again, _ = surface.solve(tr)
        ia, ib = inversion_report(V, a, T), inversion_report(V, b, T)
        rows.append(
            (
                int(frame),
                ia.n_inverted,
                ia.det.min(),
                residual(a, tr),
                np.median(times["hard"]) * 1e3,
                ib.n_inverted,
                ib.det.min(),
                stats["surface_residual"],
                np.median(times["surface"]) * 1e3,
                stats["iterations"],
                stats["barrier_tets"],
                bool(np.array_equal(again, b)),
            )
        )
    print(
        "| frame | inverted tets, hard | min det F | surface residual | solve ms | inverted tets, surface ARAP | "
        "min det F | surface residual | solve ms | iterations | tets under the barrier | same result twice |"
    )
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |")
    for r in rows:
        print(
            f"| {r[0]} | {r[1]} | {r[2]:.3f} | {r[3]:.2%} | {r[4]:.1f} | "
            f"{r[5]} | {r[6]:.3f} | {r[7]:.2%} | {r[8]:.1f} | "
            f"{r[9]} | {r[10]} | {'yes' if r[11] else 'NO'} |"
        )
    print(
        f"\nhard: {sum(r[1] > 0 for r in rows)} of {len(rows)} frames with inverted tets "
        f"({sum(r[1] for r in rows)} in all), "
        f"surface residual up to {max(r[3] for r in rows):.2%}, solve median {np.median([r[4] for r in rows]):.1f} ms, "
        f"max {max(r[4] for r in rows):.1f} ms"
    )
    print(
        f"surface ARAP: {sum(r[5] > 0 for r in rows)} of {len(rows)} frames with inverted tets "
        f"({sum(r[5] for r in rows)} in all), "
        f"surface residual up to {max(r[7] for r in rows):.2%}, solve median {np.median([r[8] for r in rows]):.1f} ms, "
        f"max {max(r[8] for r in rows):.1f} ms"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
