#!/usr/bin/env python3
"""Bake Volume's figures (issue 32): faithfulness of the baked OpenVDB in Cycles, bake time, file size, memory.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/bake_volume.py --demo DEMO_DIR \
        [--resolutions 128 256 512] [--samples 64] [--out DIR]
    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/bake_volume.py --fox FOX.ckpt \
        [--data ../shared/datasets/fox --downscale 4 --views 0 3] [--resolutions 128 256] [--samples 64]

--demo: a `make demo` output folder (demo.blend: a NeRF, its cage, two keyed handles). In the bpy
module with the add-on and its real worker, at the first frame (rest) and the last (bent): the
NeRF Deform engine's F12 is the reference; then for each resolution Bake Volume of that frame
(the NeRF's box, the Emission-Absorption material) in a fresh worker, its time (the worker's
answer), the .vdb's size and the worker's peak memory (VmHWM), and Cycles' render of the Volume
object alone through the same camera (--samples samples, no denoising): PSNR over RGBA
(premultiplied, scene-linear, as both write it) and over alpha alone.

--fox: a NeRF of instant-ngp's fox (`tools/bench/nerf_train.py ... --save FOX.ckpt`), its head
(an oriented box around tools/bench/edit_region.py's HEAD_POINT, in the wall's frame) baked by
the engine in this process and written by the add-on's writer; the reference is the engine's
render of the NeRF with every sample outside the head's box dropped (the NeRF restricted to what
was baked), from the dataset's cameras --views (photos of the capture); Cycles renders the
volume through a Blender camera made from the same intrinsics; PSNR over the whole photo and
over the pixels the head covers in either. Prints one JSON line per row.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


def psnr(a, b) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else 10 * math.log10(1.0 / mse)


def render_rgba(bpy, path: Path) -> np.ndarray:
    """F12 into a 32-bit multilayer EXR, read back: (H, W, 4) premultiplied scene-linear RGBA."""
    import OpenEXR

    scene = bpy.context.scene
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.image_settings.file_format = "OPEN_EXR_MULTILAYER"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = str(path)
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    with OpenEXR.File(str(path), separate_channels=True) as exr:
        channels = {name.split(".", 1)[1]: ch.pixels for part in exr.parts for name, ch in part.channels.items()}
    return np.stack([channels[f"Combined.{c}"] for c in "RGBA"], -1).astype(np.float64)


def cycles(bpy, samples: int) -> None:
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device, scene.cycles.samples, scene.cycles.use_denoising = "CPU", samples, False
    scene.render.film_transparent = True


def peak_memory_mib(pid: int) -> float | None:
    try:
        with open(f"/proc/{pid}/status") as f:
            return next(int(line.split()[1]) / 1024 for line in f if line.startswith("VmHWM:"))
    except (OSError, StopIteration):
        return None


def demo_rows(args, work: Path) -> list[dict]:
    import bpy

    import blender_nerf_deform
    from blender_nerf_deform.addon import api
    from blender_nerf_deform.addon.worker import jobs

    blender_nerf_deform.register()
    bpy.ops.wm.open_mainfile(filepath=str(Path(args.demo) / "demo.blend"))
    scene = bpy.context.scene
    nerf = next(o for o in scene.objects if o.nerf_deform.role == "NERF")
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = True
    rows = []
    for frame in (scene.frame_start, scene.frame_end):
        scene.render.engine = "NERF_DEFORM"
        nerf.hide_render = False
        scene.frame_set(frame)
        reference = render_rgba(bpy, work / f"engine_{frame}.exr")
        for resolution in args.resolutions:
            client = jobs.worker(bpy.context)
            client.stop()  # a fresh worker: its peak memory is this bake's (and the NeRF's)
            scene.render.engine = "NERF_DEFORM"
            nerf.hide_render = False
            folder = work / f"vdb_{frame}_{resolution}"
            t0 = time.perf_counter()
            volume = api.bake_volume(nerf, str(folder), resolution=resolution)
            wall = time.perf_counter() - t0
            pid = jobs.worker(bpy.context).call("info")[0]["pid"]
            file = next(folder.glob("*.vdb"))
            nerf.hide_render = True
            cycles(bpy, args.samples)
            t0 = time.perf_counter()
            image = render_rgba(bpy, work / f"cycles_{frame}_{resolution}.exr")
            row = {
                "case": "demo",
                "frame": frame,
                "resolution": resolution,
                "bake_s": round(wall, 2),
                "vdb_mib": round(file.stat().st_size / 2**20, 2),
                "worker_peak_mib": peak_memory_mib(pid),
                "cycles_s": round(time.perf_counter() - t0, 1),
                "samples": args.samples,
                "image": list(reference.shape[:2]),
                "psnr_rgba_db": round(psnr(image, reference), 2),
                "psnr_alpha_db": round(psnr(image[..., 3], reference[..., 3]), 2),
            }
            print(json.dumps(row), flush=True)
            rows.append(row)
            bpy.data.objects.remove(volume)
    return rows


HEAD_SIZE = (1.8, 1.8, 1.9)  # the head's box in the wall's frame, around HEAD_POINT (ears to nose)


def fox_rows(args, work: Path) -> list[dict]:
    import bpy

    import torch
    from mathutils import Matrix

    import blender_nerf_deform
    from blender_nerf_deform.addon.data.images import srgb_to_linear
    from blender_nerf_deform.addon.export.bake_volume import volume_object
    from blender_nerf_deform.addon.export.volume_file import write_vdb
    from blender_nerf_deform.engine.bend.baked_volume import volume_grid
    from blender_nerf_deform.engine.bend.volume import bake_volume
    from blender_nerf_deform.engine.geometry.region import EditRegion
    from blender_nerf_deform.engine.nerf.checkpoint import load_nerf
    from blender_nerf_deform.engine.nerf.dataset import load_dataset
    from blender_nerf_deform.engine.nerf.renderer import render_image
    from tools.bench.edit_region import HEAD_POINT, wall_frame

    bpy.ops.wm.read_factory_settings(use_empty=True)
    blender_nerf_deform.register()
    model = load_nerf(args.fox, device="cpu")
    head = EditRegion(center=HEAD_POINT, size=np.array(HEAD_SIZE), rotation=wall_frame())
    centre = torch.as_tensor(head.center, dtype=torch.float32)
    rotation = torch.as_tensor(head.rotation, dtype=torch.float32)
    half = torch.as_tensor(head.half, dtype=torch.float32)

    def only_the_head(positions, dirs):  # the NeRF restricted to the baked box: the reference
        return positions, dirs, (((positions - centre) @ rotation).abs() <= half).all(dim=-1)

    ds = load_dataset(args.data, downscale=args.downscale, load_images=False)
    scene = bpy.context.scene
    nerf = bpy.data.objects.new("Fox", None)
    scene.collection.objects.link(nerf)
    rows = []
    for resolution in args.resolutions:
        grid = volume_grid(head, resolution)
        t0 = time.perf_counter()
        baked = bake_volume(model, grid)
        bake_s = time.perf_counter() - t0
        path = work / f"fox_head_{resolution}.vdb"
        write_vdb(path, grid.shape, grid.index_to_nerf, baked.index, baked.density, srgb_to_linear(baked.color))
        volume = volume_object(bpy.context, nerf, path, [1], "EMISSION")
        for view in args.views:
            cam = ds.cameras[view]
            reference = render_image(model, cam, sample_transform=only_the_head)["rgba"].astype(np.float64)
            reference = np.concatenate(
                [srgb_to_linear(reference[..., :3]) * reference[..., 3:], reference[..., 3:]], -1
            )
            data = bpy.data.cameras.new(f"View {view}")
            data.sensor_fit, data.angle_x = "HORIZONTAL", 2 * math.atan(0.5 * cam.width / cam.fx)
            data.shift_x = (0.5 * cam.width - cam.cx) / cam.width
            data.shift_y = (cam.cy - 0.5 * cam.height) / cam.width
            data.clip_start = 0.01
            camera = bpy.data.objects.new(f"View {view}", data)
            scene.collection.objects.link(camera)
            camera.matrix_world = Matrix(np.asarray(cam.c2w).tolist())
            scene.camera = camera
            scene.render.resolution_x, scene.render.resolution_y = cam.width, cam.height
            scene.render.resolution_percentage = 100
            cycles(bpy, args.samples)
            image = render_rgba(bpy, work / f"fox_{resolution}_{view}.exr")
            row = {
                "case": "fox head",
                "view": view,
                "resolution": resolution,
                "grid": list(grid.shape),
                "bake_s": round(bake_s, 2),
                "vdb_mib": round(path.stat().st_size / 2**20, 2),
                "samples": args.samples,
                "image": [cam.height, cam.width],
                "psnr_rgba_db": round(psnr(image, reference), 2),
                "psnr_alpha_db": round(psnr(image[..., 3], reference[..., 3]), 2),
            }
            # The head covers a part of the photo: also over the pixels either image covers.
            covered = (image[..., 3] > 0.01) | (reference[..., 3] > 0.01)
            row["covered_pixels"] = int(covered.sum())
            row["psnr_rgba_covered_db"] = round(psnr(image[covered], reference[covered]), 2)
            print(json.dumps(row), flush=True)
            rows.append(row)
        bpy.data.objects.remove(volume)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--demo", help="a `make demo` output folder (its demo.blend)")
    what.add_argument("--fox", help="a checkpoint trained on instant-ngp's fox")
    p.add_argument("--data", default=str(REPO.parent / "shared" / "datasets" / "fox"), help="the fox dataset (--fox)")
    p.add_argument("--downscale", type=int, default=4, help="the fox's cameras at 1/K (default 4)")
    p.add_argument("--views", type=int, nargs="+", default=[0, 3], help="the fox's views rendered (default 0 3)")
    p.add_argument(
        "--resolutions",
        type=int,
        nargs="+",
        default=None,
        help="voxels along the box's longest side (default 128 256 512 for --demo, 128 256 for --fox)",
    )
    p.add_argument("--samples", type=int, default=64, help="Cycles samples per pixel (default 64)")
    p.add_argument("--out", type=Path, help="keep the frames and files here (default: a temporary folder, removed)")
    args = p.parse_args(argv)
    args.resolutions = args.resolutions or ([128, 256, 512] if args.demo else [128, 256])
    work = args.out or Path(tempfile.mkdtemp(prefix="bench_bake_volume_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        rows = demo_rows(args, work) if args.demo else fox_rows(args, work)
    finally:
        if args.out is None:
            shutil.rmtree(work, ignore_errors=True)
    print(f"machine: {os.cpu_count()} cores; {len(rows)} rows")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
