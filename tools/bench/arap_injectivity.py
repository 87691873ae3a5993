#!/usr/bin/env python3
"""Inverted cage tets and solve time per frame of `make demo`'s animation: ARAP alone vs ARAP + the
flip-free step (engine/geometry/injective.py), on the demo's own cage, regions and handle poses.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/arap_injectivity.py [--demo demo_out]
        [--poses POSES.npz] [--save-poses POSES.npz] [--repeat 3]

The poses come from demo.blend as a render reads them: the bpy module opens it with the demo's
private Blender user folder (the extension enabled, as `tools/demo.py`'s render stage starts), and
for every frame the add-on's own `deformation.handle_pose` gives the handles' transforms (NeRF
frame) and the shared content (cage, embedding, regions) a render request carries. `--save-poses`
keeps them in an .npz, and `--poses` reads one instead of the .blend (no bpy needed).

Each frame is then solved as the worker's render op solves it (`RegionDeformer` built from the
same arrays, `solve(transforms)`), once with `injective=False` (ARAP alone, what `make demo` ran
before) and once with the step; inverted tets are counted as the renderer counts them
(`barycentric.inversion_report`, det F < -1e-6). Times are the median of --repeat solves per frame,
after one warm-up solve (numba kernels compiled, the factorizations made).
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
        transforms.append(np.asarray(pose["transforms"], dtype=np.float64))
        if not out:
            out = {"mode": np.array(pose["mode"])}
            for name in ("cage", "embedding", "regions"):
                for k, v in shared[name][1]().items():
                    out[f"{name}.{k}"] = np.asarray(v)
    out["transforms"] = np.stack(transforms)
    out["frames"] = np.arange(scene.frame_start, scene.frame_end + 1)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--demo", type=Path, default=REPO / "demo_out", help="make demo's output folder (default demo_out/)")
    ap.add_argument("--poses", type=Path, help="an .npz written by --save-poses (instead of demo.blend)")
    ap.add_argument("--save-poses", type=Path, help="write the poses read from demo.blend to this .npz")
    ap.add_argument("--repeat", type=int, default=3, help="timed solves per frame and variant (median)")
    args = ap.parse_args()

    data = dict(np.load(args.poses)) if args.poses else poses_from_blend(args.demo.resolve())
    if args.save_poses:
        np.savez_compressed(args.save_poses, **data)

    from geometry_common import machine
    from blender_nerf_deform.engine.geometry.barycentric import inversion_report
    from blender_nerf_deform.engine.geometry.deform import RegionDeformer, split_regions
    from blender_nerf_deform.engine.geometry.embedding import Embedding

    V, T = data["cage.vertices"].astype(np.float64), data["cage.tets"].astype(np.int64)
    tet_ids = data["embedding.tet_ids"]
    embedding = Embedding(tet_ids=tet_ids, corners=T[tet_ids], weights=data["embedding.weights"], n_outside=0)
    regions = split_regions(data["regions.handle_index"], data["regions.handle_counts"])
    print(f"machine: {machine()}; cage {len(V)} vertices, {len(T)} tets; {len(regions)} handles, "
          f"{len(data['transforms'])} frames", flush=True)

    def build(injective):
        return RegionDeformer(V, T, embedding, regions, data["regions.pin_index"], mode=str(data["mode"]),
                              cage_pins=data.get("regions.cage_pin_index"), injective=injective)

    plain, step = build(False), build(True)
    plain.solve(list(data["transforms"][-1]))  # warm-up: kernels, factorizations
    step.solve(list(data["transforms"][-1]))
    rows = []
    for frame, transforms in zip(data["frames"], data["transforms"]):
        tr = list(transforms)
        times = {"arap": [], "step": []}
        for _ in range(max(1, args.repeat)):
            t0 = time.perf_counter()
            a, _ = plain.solve(tr)
            times["arap"].append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            b, stats = step.solve(tr)
            times["step"].append(time.perf_counter() - t0)
        again, _ = step.solve(tr)
        ia, ib = inversion_report(V, a, T), inversion_report(V, b, T)
        moved = float(np.abs(b - a).max()) / plain.arap.diag
        rows.append((int(frame), ia.n_inverted, ia.det.min(), ib.n_inverted, ib.det.min(),
                     np.median(times["arap"]) * 1e3, np.median(times["step"]) * 1e3,
                     stats.get("injective_iterations", 0), stats.get("injective_start", "-"),
                     stats.get("handle_residual", 0.0), moved, bool(np.array_equal(again, b))))
    print("| frame | inverted tets, ARAP alone | min det F | inverted tets, ARAP + step | min det F | solve ms, ARAP alone | "
          "solve ms, ARAP + step | step iterations | step's start | handle residual (/ diagonal) | "
          "largest vertex change (/ diagonal) | same result twice |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: | --- |")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]:.3f} | {r[3]} | {r[4]:.3f} | {r[5]:.1f} | {r[6]:.1f} | {r[7]} | {r[8]} | "
              f"{r[9]:.1e} | {r[10]:.2e} | {'yes' if r[11] else 'NO'} |")
    bent = [r for r in rows if r[1] > 0]
    print(f"\nframes with inverted tets: ARAP alone {len(bent)} of {len(rows)} ({sum(r[1] for r in rows)} tets in all, "
          f"at most {max((r[1] for r in rows), default=0)}); ARAP + step {sum(r[3] > 0 for r in rows)} "
          f"({sum(r[3] for r in rows)} tets)")
    if bent:
        print(f"solve time on those frames: ARAP alone median {np.median([r[5] for r in bent]):.1f} ms, "
              f"ARAP + step median {np.median([r[6] for r in bent]):.1f} ms, max {max(r[6] for r in bent):.1f} ms")
    fine = [r for r in rows if r[1] == 0]
    if fine:
        print(f"frames ARAP already gets right: largest vertex change by the step {max(r[10] for r in fine):.1e} of the "
              f"cage's diagonal; solve median {np.median([r[5] for r in fine]):.1f} ms alone, "
              f"{np.median([r[6] for r in fine]):.1f} ms with the step")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
