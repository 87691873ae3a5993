#!/usr/bin/env python3
"""Benchmark: one 1920x1080 frame (issue 18, resolution), undeformed and ray-bent, demo scene and lego.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/frame_1080.py --demo demo_out \\
        --lego-run /work/runs/lego_1080 --lego-data ../shared/datasets/lego_200 --paths legacy fast

- demo (`make demo`'s demo.blend): the scene camera at --width x --height (the same horizontal field
  of view: Blender's sensor fit), in the NeRF's frame, as the RenderEngine builds the request
  (`frame_render.camera_request`); the bent pose is the last keyframe's: its handle transforms,
  solved by ARAP (`RegionDeformer`, what the worker's render op runs). The .blend is read once by
  a child process with the bpy module (`--child-extract`; no torch in that process) and cached
  as an .npz beside the checkpoint.
- lego: the checkpoint of `--lego-run` (nerf.ckpt + cage.npz), the dataset's camera `--lego-view`
  at --width x --height with its horizontal field of view; the bent pose is
  tools/bench/bending.py's twist (30 degrees of the upper half).

Per scene and render path (`--paths`: `legacy` = the renderer as it was before this issue, 4096-ray
row chunks and its round schedule; `fast` = the default now), each of `--reps` repetitions
renders the undeformed frame and the bent frame alternately; reported: seconds (median),
ms per megapixel, density / colour samples per ray, and for the bent frame the posing
(ARAP solve + `CageBend.set_deformed`) and the ratio bent/undeformed with posing counted, all
from the same run. Peak RSS per process at the end. The PSNR of the fast path against
the legacy path (same frame) is reported for every frame.
"""

from __future__ import annotations

DEVICE = "cpu"  # where the NeRF renders (--device)

import argparse
import json
import math
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


# --------------------------------------------------------------------------- child: read the .blend (bpy, no torch)


def child_extract(blend: str, out: str, width: int, height: int) -> int:
    import bpy

    import blender_nerf_deform

    blender_nerf_deform.register()
    try:
        bpy.ops.wm.open_mainfile(filepath=blend)
        from blender_nerf_deform.addon.render.frame import camera_request, nerf_pose, nerfs_to_render, scene_pinhole

        scene = bpy.context.scene
        scene.render.resolution_x, scene.render.resolution_y = width, height
        scene.render.resolution_percentage = 100
        result = {}
        for which, frame in (("rest", scene.frame_start), ("bent", scene.frame_end)):
            scene.frame_set(frame)
            depsgraph = bpy.context.evaluated_depsgraph_get()
            nerf = nerfs_to_render(depsgraph)[0]
            posed = nerf_pose(depsgraph, nerf)
            request = camera_request(posed, scene_pinhole(depsgraph))
            result[f"{which}_params"] = request.params
            if which == "bent":
                if request.params["pose"]["kind"] != "handles":
                    raise SystemExit(f"demo: the last frame's pose is {request.params['pose']['kind']!r}, not handles")
                for slot, (_key, load) in request.shared.items():
                    for name, array in load().items():
                        result[f"{slot}/{name}"] = np.asarray(array)
        arrays = {k: v for k, v in result.items() if isinstance(v, np.ndarray)}
        meta = {k: v for k, v in result.items() if not isinstance(v, np.ndarray)}
        np.savez(out, meta=np.array(json.dumps(meta)), **arrays)
    finally:
        blender_nerf_deform.unregister()
    return 0


# --------------------------------------------------------------------------- the benchmark (torch, no bpy)


def psnr(a, b) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else -10 * math.log10(mse)


def demo_scene(demo: Path, width: int, height: int):
    """(checkpoint, camera, pose function () -> (deformed vertices, solve seconds), rest vertices, tets)."""
    from blender_nerf_deform.engine.geometry.deform import split_regions
    from blender_nerf_deform.engine.geometry.embedding import Embedding
    from blender_nerf_deform.engine.geometry.handle_pose import RegionDeformer
    from blender_nerf_deform.engine.service.requests import WireCamera

    blend = demo / "demo.blend"
    cache = demo / f"bench_frame_{width}x{height}.npz"
    if not cache.is_file() or cache.stat().st_mtime < blend.stat().st_mtime:
        proc = subprocess.run(
            [sys.executable, __file__, "--child-extract", str(blend), str(cache), str(width), str(height)],
            cwd=REPO,
            capture_output=True,
            text=True,
        )
        if proc.returncode != 0:
            raise SystemExit(f"reading {blend} failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}")
    data = np.load(cache)
    meta = json.loads(str(data["meta"]))
    params = meta["bent_params"]
    camera = WireCamera.from_wire(params["camera"]).camera()
    pose = params["pose"]
    rest, tets = data["cage/vertices"], data["cage/tets"]
    tet_ids = data["embedding/tet_ids"]
    embedding = Embedding(tet_ids=tet_ids, corners=tets[tet_ids], weights=data["embedding/weights"], n_outside=0)
    regions = split_regions(data["regions/handle_index"], data["regions/handle_counts"])
    t0 = time.perf_counter()
    deformer = RegionDeformer(
        rest,
        tets,
        embedding,
        regions,
        data["regions/pin_index"],
        pose.get("handle_names") or None,
        pose.get("mode", "ARAP"),
        cage_pins=data["regions/cage_pin_index"],
    )
    precompute_s = time.perf_counter() - t0
    transforms = [np.asarray(t, dtype=np.float64) for t in pose["transforms"]]

    def solve():
        t = time.perf_counter()
        deformed, stats = deformer.solve(transforms)
        return np.asarray(deformed, dtype=np.float64), time.perf_counter() - t

    return params["checkpoint"], camera, solve, rest, tets, {"arap_precompute_s": precompute_s, "tets": int(len(tets))}


def lego_scene(run: Path, data: str, view: int, width: int, height: int):
    from dataclasses import replace

    from blender_nerf_deform.engine.geometry.mesh_io import load_cage
    from blender_nerf_deform.engine.nerf.dataset import load_dataset
    from tools.bench.bending import twist_upper_part

    ds = load_dataset(data)
    cam = ds.cameras[view]
    f = cam.fx * width / cam.width  # the same horizontal field of view
    camera = replace(cam, width=width, height=height, fx=f, fy=f, cx=width / 2, cy=height / 2)
    cage = load_cage(run / "cage.npz")
    rest, tets = cage["vertices"], cage["tets"]
    deformed = twist_upper_part(rest, 30.0, 0.5)
    return str(run / "nerf.ckpt"), camera, (lambda: (deformed, 0.0)), rest, tets, {"tets": int(len(tets))}


def bench_scene(name, scene, paths, reps, save: Path | None, no_step_refine: bool = False):
    import torch

    from blender_nerf_deform.engine.bend.posed import PosedRenderer
    from blender_nerf_deform.engine.nerf import renderer
    from blender_nerf_deform.engine.nerf.checkpoint import load_nerf

    ckpt, camera, solve, rest, tets, info = scene
    model = load_nerf(ckpt, device=DEVICE)
    mp = camera.width * camera.height / 1e6
    posed = PosedRenderer(model, rest, tets)
    deformed, _ = solve()
    # Warm-up (numba compilation, allocator) on a small frame of the same camera.
    from dataclasses import replace

    small = replace(
        camera,
        width=camera.width // 8,
        height=camera.height // 8,
        fx=camera.fx / 8,
        fy=camera.fy / 8,
        cx=camera.cx / 8,
        cy=camera.cy / 8,
    )
    for path in paths:
        with renderer.render_path(path):
            PosedRenderer(model).render(small)
            posed.render(small, deformed)
    rows, images = [], {}
    for path in paths:
        times = {"plain": [], "bent": [], "pose": [], "solve": []}
        for rep in range(reps):
            order = ("plain", "bent") if rep % 2 == 0 else ("bent", "plain")
            for mode in order:
                with renderer.render_path(path):
                    if mode == "plain":
                        t = time.perf_counter()
                        out = PosedRenderer(model).render(camera)
                        times["plain"].append(time.perf_counter() - t)
                    else:
                        posed._pose = None  # a new pose every frame: posing counted
                        t = time.perf_counter()
                        deformed, solve_s = solve()
                        posed.bend.set_deformed(deformed)
                        posed._pose = deformed.copy()
                        if no_step_refine:  # CageBend's finer step for compressed poses, off (to measure it)
                            posed.bend.step_refine = 1.0
                        t2 = time.perf_counter()
                        out = posed.render(camera, deformed)
                        t3 = time.perf_counter()
                        times["bent"].append(t3 - t2)
                        times["pose"].append(t2 - t)
                        times["solve"].append(solve_s)
                if rep == 0:
                    images[(path, mode)] = out
        med = {k: float(np.median(v)) for k, v in times.items()}
        for mode in ("plain", "bent"):
            out = images[(path, mode)]
            row = {
                "scene": name,
                "path": path,
                "frame": "bent" if mode == "bent" else "undeformed",
                "size": f"{camera.width}x{camera.height}",
                "seconds": med[mode],
                "ms_per_mp": 1e3 * med[mode] / mp,
                "density_samples_per_ray": out["density_samples_per_ray"],
                "color_samples_per_ray": out["color_samples_per_ray"],
                "alpha_mean": float(out["rgba"][..., 3].mean()),
            }
            if mode == "bent":
                row.update(
                    pose_seconds=med["pose"],
                    arap_solve_seconds=med["solve"],
                    seconds_with_pose=med["bent"] + med["pose"],
                    ratio_bent_over_undeformed=med["bent"] / med["plain"],
                    ratio_with_pose=(med["bent"] + med["pose"]) / med["plain"],
                    inverted_tets=int(out["inversion"].n_inverted) if out["inversion"] is not None else None,
                    step_refine=float(getattr(posed.bend, "step_refine", 1.0)),
                )
            rows.append(row)
            if save is not None:
                from blender_nerf_deform.engine.cli.render import write_png_rgba

                save.mkdir(parents=True, exist_ok=True)
                write_png_rgba(save / f"{name}_{path}_{row['frame']}.png", out["rgba"])
    if "legacy" in paths:
        for row in rows:
            if row["path"] != "legacy":
                ref = images[("legacy", "bent" if row["frame"] == "bent" else "plain")]
                mine = images[(row["path"], "bent" if row["frame"] == "bent" else "plain")]
                row["psnr_vs_legacy_rgba"] = psnr(mine["rgba"], ref["rgba"])
    del torch
    return rows, info


def dataset_psnr(run: Path, data: str, views: int, paths) -> dict:
    """Every `len / views`-th view of the dataset at its own size on each path: PSNR (white background) vs
    the dataset's image, vs the legacy path, seconds and samples per ray (means over the views)."""
    from blender_nerf_deform.engine.nerf import renderer
    from blender_nerf_deform.engine.nerf.checkpoint import load_nerf
    from blender_nerf_deform.engine.nerf.dataset import load_dataset

    model = load_nerf(str(run / "nerf.ckpt"), device="cpu")
    ds = load_dataset(data)
    ds = ds.subset(range(0, len(ds), max(1, len(ds) // views)))
    out = {}
    frames = {}
    for path in paths:
        with renderer.render_path(path):
            renderer.render_image(model, ds.cameras[0])
            rows = []
            for k, (cam, img) in enumerate(zip(ds.cameras, ds.images)):
                t = time.perf_counter()
                o = renderer.render_image(model, cam, background=(1.0, 1.0, 1.0))
                s = time.perf_counter() - t
                gt = img[..., :3] * img[..., 3:] + (1 - img[..., 3:])
                frames[(path, k)] = o["rgba"]
                rows.append(
                    (
                        psnr(o["rgb"], gt),
                        s,
                        o["density_samples_per_ray"],
                        o["color_samples_per_ray"],
                        psnr(o["rgba"], frames[("legacy", k)])
                        if ("legacy", k) in frames and path != "legacy"
                        else None,
                    )
                )
        out[path] = {
            "views": len(rows),
            "size": f"{ds.width}x{ds.height}",
            "psnr_vs_dataset_white": float(np.mean([r[0] for r in rows])),
            "seconds_median": float(np.median([r[1] for r in rows])),
            "density_samples_per_ray": float(np.mean([r[2] for r in rows])),
            "color_samples_per_ray": float(np.mean([r[3] for r in rows])),
        }
        if rows[0][4] is not None:
            out[path]["psnr_rgba_vs_legacy_min"] = float(np.min([r[4] for r in rows]))
    return out


def main(argv=None) -> int:
    if argv is None and len(sys.argv) > 1 and sys.argv[1] == "--child-extract":
        return child_extract(sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5]))
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--demo", type=Path, help="make demo's output folder (demo.blend, run/nerf.ckpt)")
    ap.add_argument("--lego-run", type=Path, help="folder with nerf.ckpt and cage.npz of a lego NeRF")
    ap.add_argument("--lego-data", default="../shared/datasets/lego_200")
    ap.add_argument("--lego-view", type=int, default=0)
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--paths", nargs="+", default=["legacy", "fast"], help="render paths to compare (legacy, fast)")
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--save", type=Path, help="folder for the frames (PNG)")
    ap.add_argument(
        "--no-step-refine",
        action="store_true",
        help="bent frames march at the NeRF's step even where the pose compresses it (CageBend.step_refine = 1)",
    )
    ap.add_argument(
        "--psnr-views",
        type=int,
        default=0,
        help="also render this many lego dataset views at the dataset's size on every path: PSNR vs the "
        "dataset (white) and vs the legacy path",
    )
    ap.add_argument("--json", type=Path)
    ap.add_argument("--device", default="cpu", help="cpu or cuda (the torch path)")
    args = ap.parse_args(argv)
    global DEVICE
    DEVICE = args.device
    if not (args.demo or args.lego_run):
        ap.error("give --demo and/or --lego-run")
    import torch

    results = {"threads": torch.get_num_threads(), "scenes": {}, "rows": []}
    if args.demo:
        rows, info = bench_scene(
            "demo",
            demo_scene(args.demo, args.width, args.height),
            args.paths,
            args.reps,
            args.save,
            args.no_step_refine,
        )
        results["rows"] += rows
        results["scenes"]["demo"] = info
    if args.lego_run:
        rows, info = bench_scene(
            "lego",
            lego_scene(args.lego_run, args.lego_data, args.lego_view, args.width, args.height),
            args.paths,
            args.reps,
            args.save,
            args.no_step_refine,
        )
        results["rows"] += rows
        results["scenes"]["lego"] = info
        if args.psnr_views:
            results["lego_dataset_psnr"] = dataset_psnr(args.lego_run, args.lego_data, args.psnr_views, args.paths)
    results["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(json.dumps(results, indent=1))
    for r in results["rows"]:
        extra = ""
        if r["frame"] == "bent":
            extra = (
                f"  pose {r['pose_seconds']:.3f} s (ARAP {r['arap_solve_seconds']:.3f})"
                f"  with pose {r['seconds_with_pose']:.2f} s"
                f"  ratio {r['ratio_bent_over_undeformed']:.3f} / with pose {r['ratio_with_pose']:.3f}"
            )
        if "psnr_vs_legacy_rgba" in r:
            extra += f"  PSNR vs legacy {r['psnr_vs_legacy_rgba']:.1f} dB"
        print(
            f"{r['scene']:5s} {r['path']:7s} {r['frame']:10s} {r['seconds']:7.2f} s  {r['ms_per_mp']:7.0f} ms/MP  "
            f"{r['density_samples_per_ray']:6.2f} / {r['color_samples_per_ray']:5.2f} samples/ray{extra}"
        )
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
