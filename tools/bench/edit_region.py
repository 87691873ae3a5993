#!/usr/bin/env python3
"""Edit one object of a real capture: the fox's head turned on its plaque (issue 14's figures).

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/edit_region.py --nerf FOX.ckpt \
        [--data ../shared/datasets/fox --downscale 4 --view 0 --resolution 192 --angle 30 --out DIR]

Two parts, on a NeRF trained on instant-ngp's fox (`tools/bench/nerf_train.py --data
../shared/datasets/fox --downscale 4 --seconds 600 --save FOX.ckpt`):

1. The command line, timed: `extract` over the NeRF's whole inner box, then `cage` on it;
   `extract --region --pick` inside the fox's region, then `cage --region`. Sizes and times
   of both (the whole box holds the room's walls: its cage may take long or fail, which is
   the point of a region; it is given --cage-timeout seconds).
2. Blender (the bpy module, the add-on with its real worker), as an artist would: Load NeRF,
   Add Edit Region (set to FOX_REGION), the 3D cursor on the fox's head with "Pick at 3D
   Cursor", Extract Mesh, Build Cage (the cut pinned), the head's vertices selected, Add
   Handle, a Blender camera at the dataset's view --view, F12 (the NeRF Deform RenderEngine)
   at rest, the handle turned --angle degrees about the capture's up axis, F12 again. Both
   frames are read back as float EXR.

Measured on the two frames: PSNR over the pixels whose rays never enter the rest or the
deformed cage (their projections rasterized, dilated by 2 px: target >= 45 dB); the mean
colour / alpha change inside the head's projection (the head moved); NaN count; the smallest
alpha inside the plaque's outline (the projection of the surface within PLAQUE_DEPTH of the
wall: no hole at the cut means >= 0.5). Prints one JSON line with everything, and writes the
frames and masks as PNGs into --out.

FOX_REGION and the wall plane come from this dataset's geometry (the fox's world frame is its
transforms.json's): the wall was fitted (RANSAC + SVD) to the depth of view 0 around the
plaque, and the region is the box in the wall's frame (x along the wall, y up, z out of it)
from just off the wall (it cuts the plaque's back: the cut) out past the nose.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

# The wall behind the fox: unit normal n (out of the wall, towards the cameras) and offset d,
# n . p + d = 0 on the wall (fitted on view 0's depth, 10k inliers within 0.03).
WALL_NORMAL = np.array([0.8767474, -0.47221208, -0.09126732])
WALL_OFFSET = -0.18368396
# Local box in the wall's frame (x = up x n, y = world up projected on the wall, z = n):
# fox and plaque span x -1.45 .. 2.15, y -1.84 .. 2.46, z 0 (the wall) .. 2.6 (the nose).
FOX_LOCAL_BOX = ((-1.7, -2.1, 0.06), (2.4, 2.7, 2.9))
HEAD_POINT = np.array([1.70, -1.50, 0.55])  # between the eyes and the ears, on the head's surface
HEAD_RADIUS = 0.75  # the head handle: surface vertices within this of HEAD_POINT
PLAQUE_DEPTH = 0.5  # surface vertices this close to the wall are the plaque


def wall_frame() -> np.ndarray:
    """Rotation whose columns are the wall's (along, up, out) axes, in the NeRF's frame."""
    n = WALL_NORMAL / np.linalg.norm(WALL_NORMAL)
    up = np.array([0.0, 0.0, 1.0]) - n[2] * n
    up /= np.linalg.norm(up)
    return np.stack([np.cross(up, n), up, n], axis=1)


def fox_region() -> dict:
    from blender_nerf_deform.engine.geometry.region import EditRegion

    R = wall_frame()
    lo, hi = (np.array(v) for v in FOX_LOCAL_BOX)
    origin = -WALL_OFFSET * WALL_NORMAL / np.linalg.norm(WALL_NORMAL)
    center = origin + R @ (0.5 * (lo + hi))
    return EditRegion(center=center, size=hi - lo, rotation=R).to_dict()


# -- part 1: the command line -------------------------------------------------------------


def _timed(cmd, timeout=None) -> tuple[float, subprocess.CompletedProcess | None]:
    t0 = time.perf_counter()
    try:
        proc = subprocess.run([str(c) for c in cmd], cwd=REPO, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return time.perf_counter() - t0, None
    return time.perf_counter() - t0, proc


def command_line(args, work: Path, region_json: Path) -> dict:
    from blender_nerf_deform.engine.geometry.mesh_io import load_cage, read_ply

    engine = [sys.executable, "-m", "blender_nerf_deform.engine"]
    out = {}
    for label, extra_extract, extra_cage in (
        ("whole box", [], []),
        ("region", ["--region", region_json, "--pick", *map(str, HEAD_POINT)], ["--region", region_json]),
    ):
        mesh, cage = work / f"{label.replace(' ', '_')}.ply", work / f"{label.replace(' ', '_')}.npz"
        row = {}
        t, proc = _timed(
            [*engine, "extract", "--nerf", args.nerf, "--out", mesh, "--resolution", args.resolution, *extra_extract]
        )
        if proc is None or proc.returncode != 0:
            row["extract_error"] = (proc.stderr.strip().splitlines() or ["?"])[-1] if proc else "timeout"
            out[label] = row
            continue
        v, f, _c = read_ply(mesh)
        row.update(extract_s=round(t, 1), vertices=len(v), faces=len(f))
        t, proc = _timed(
            [*engine, "cage", "--nerf", args.nerf, "--mesh", mesh, "--out", cage, *extra_cage],
            timeout=args.cage_timeout,
        )
        if proc is None:
            row["cage_error"] = f"not done within {args.cage_timeout} s"
        elif proc.returncode != 0:
            row["cage_error"] = (proc.stderr.strip().splitlines() or ["?"])[-1]
            row["cage_s"] = round(t, 1)
        else:
            c = load_cage(cage)
            row.update(
                cage_s=round(t, 1),
                cage_tets=len(c["tets"]),
                cage_vertices=len(c["vertices"]),
                pinned=int(len(c.get("pinned_vertices", []))),
            )
        out[label] = row
        print(f"{label}: {row}", flush=True)
    return out


# -- part 2: Blender -------------------------------------------------------------------------


def _ok(result, what):
    if result != {"FINISHED"}:
        raise SystemExit(f"{what} did not finish: {result}")


def _render_exr(bpy, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """F12 into a multilayer EXR: (rgba (H,W,4) float, rows top-down; depth (H,W))."""
    import OpenEXR

    scene = bpy.context.scene
    bpy.context.view_layer.use_pass_z = True
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.image_settings.file_format = "OPEN_EXR_MULTILAYER"
    scene.render.filepath = str(path)
    _ok(bpy.ops.render.render(write_still=True), "F12")
    passes = {}
    with OpenEXR.File(str(path), separate_channels=True) as exr:
        for part in exr.parts:
            for name, channel in part.channels.items():
                _layer, pass_name, chan = name.split(".")
                passes.setdefault(pass_name, {})[chan] = channel.pixels.copy()
    rgba = np.stack([passes["Combined"][k] for k in "RGBA"], -1)
    return rgba.astype(np.float64), next(iter(passes["Depth"].values())).astype(np.float64)


def _raster(shape, pinhole, vertices, triangles) -> np.ndarray:
    """Pixels covered by the projection of triangles (every point in front of the camera)."""
    from PIL import Image, ImageDraw

    h, w = shape
    uv = pinhole.project(vertices)
    img = Image.new("L", (w, h), 0)
    draw = ImageDraw.Draw(img)
    for tri in uv[triangles]:
        draw.polygon([tuple(p) for p in tri], fill=255)
    return np.asarray(img) > 0


def _dilate(mask, px):
    from scipy import ndimage

    return ndimage.binary_dilation(mask, iterations=px)


def blender_part(args, work: Path, region: dict) -> dict:
    os.environ.setdefault("NERF_DEFORM_PYTHON", sys.executable)
    import bpy

    from mathutils import Euler, Matrix, Vector

    import blender_nerf_deform
    from blender_nerf_deform.addon import api
    from blender_nerf_deform.addon.data.cage_store import cage_pins, load_cage
    from blender_nerf_deform.addon.data.camera import pinhole_from_blender
    from blender_nerf_deform.addon.deform import poses as deformation
    from blender_nerf_deform.addon.worker import jobs
    from blender_nerf_deform.engine.geometry.barycentric import boundary_faces
    from blender_nerf_deform.engine.nerf.dataset import load_dataset

    blender_nerf_deform.register()
    timings = {}
    try:
        bpy.ops.wm.read_factory_settings(use_empty=True)
        _ok(bpy.ops.nerf_deform.load_nerf(filepath=str(Path(args.nerf).resolve())), "Load NeRF")
        nerf = bpy.context.active_object
        nerf.matrix_world = Matrix.Identity(4)  # the NeRF's frame is the scene's: the dataset's cameras as they are
        bpy.context.view_layer.update()
        _ok(bpy.ops.nerf_deform.add_edit_region(), "Add Edit Region")
        box = nerf.nerf_deform.edit_region
        box.location = region["center"]
        box.rotation_euler = Euler(region["rotation_euler"], "XYZ")
        box.scale = region["size"]  # a new region's display size is 0.5: its scale is its size
        bpy.context.scene.cursor.location = Vector(HEAD_POINT.tolist())
        s = nerf.nerf_deform
        s.pick_object, s.pin_cut, s.resolution = True, True, int(args.resolution)
        bpy.context.view_layer.objects.active = nerf
        t0 = time.perf_counter()
        _ok(bpy.ops.nerf_deform.extract_mesh(), "Extract Mesh")
        timings["extract_s"] = time.perf_counter() - t0
        bpy.context.view_layer.objects.active = nerf
        t0 = time.perf_counter()
        _ok(bpy.ops.nerf_deform.build_cage(), "Build Cage")
        timings["cage_s"] = time.perf_counter() - t0
        surface, cage_object = s.surface, s.cage
        co = np.empty(3 * len(surface.data.vertices))
        surface.data.vertices.foreach_get("co", co)
        co = co.reshape(-1, 3)
        head = np.flatnonzero(np.linalg.norm(co - HEAD_POINT, axis=1) < HEAD_RADIUS)
        if len(head) < 20:
            raise SystemExit(f"only {len(head)} surface vertices near the head point: is this the fox?")
        handle = api.add_handle(nerf, head)  # selected in Edit Mode, Add Handle, back to Object Mode

        ds = load_dataset(args.data, downscale=args.downscale, load_images=False)
        cam = ds.cameras[args.view]
        scene = bpy.context.scene
        cam_data = bpy.data.cameras.new("View")
        cam_data.sensor_fit = "HORIZONTAL"
        cam_data.angle_x = 2 * math.atan(0.5 * cam.width / cam.fx)
        cam_data.shift_x = (0.5 * cam.width - cam.cx) / cam.width
        cam_data.shift_y = (cam.cy - 0.5 * cam.height) / cam.width
        cam_data.clip_start = 0.01
        camera = bpy.data.objects.new("View", cam_data)
        scene.collection.objects.link(camera)
        scene.camera = camera
        camera.matrix_world = Matrix(cam.c2w.tolist())
        scene.render.resolution_x, scene.render.resolution_y = cam.width, cam.height
        scene.render.pixel_aspect_y = 1.0
        scene.render.resolution_percentage = 100
        scene.render.engine = "NERF_DEFORM"
        bpy.context.view_layer.update()

        t0 = time.perf_counter()
        rest, _ = _render_exr(bpy, work / "rest.exr")
        timings["rest_frame_s"] = time.perf_counter() - t0
        up = np.mean([c.c2w[:3, 1] for c in ds.cameras], axis=0)
        up /= np.linalg.norm(up)
        turn = Matrix.Rotation(math.radians(args.angle), 4, Vector(up.tolist()))
        handle.matrix_world = (
            Matrix.Translation(handle.matrix_world.translation)
            @ turn
            @ Matrix.Translation(-handle.matrix_world.translation)
            @ handle.matrix_world
        )
        bpy.context.view_layer.update()
        t0 = time.perf_counter()
        edited, _ = _render_exr(bpy, work / "edited.exr")
        timings["edited_frame_s"] = time.perf_counter() - t0

        pinhole = pinhole_from_blender(scene, camera)
        rest_cage, tets = load_cage(cage_object.data)
        deformed = deformation.deformed_cage(nerf, bpy.context.evaluated_depsgraph_get(), jobs.worker(bpy.context))
        faces = boundary_faces(tets)
        shape = rest.shape[:2]
        cages = _dilate(_raster(shape, pinhole, rest_cage, faces) | _raster(shape, pinhole, deformed, faces), 2)
        outside = ~cages
        mse = float(np.mean((edited[outside][:, :4] - rest[outside][:, :4]) ** 2))
        psnr = float("inf") if mse == 0 else 10 * math.log10(1.0 / mse)
        surface.data.calc_loop_triangles()
        mesh_tris = np.empty(3 * len(surface.data.loop_triangles), dtype=np.int64)
        surface.data.loop_triangles.foreach_get("vertices", mesh_tris)
        mesh_tris = mesh_tris.reshape(-1, 3)
        head_tris = mesh_tris[np.isin(mesh_tris, head).all(axis=1)]
        head_px = _raster(shape, pinhole, co, head_tris)
        wall_dist = co @ WALL_NORMAL + WALL_OFFSET
        plaque = np.flatnonzero(wall_dist < PLAQUE_DEPTH)
        plaque_tris = mesh_tris[np.isin(mesh_tris, plaque).all(axis=1)]
        plaque_px = _raster(shape, pinhole, co, plaque_tris) & ~_dilate(head_px, 2)
        change = np.abs(edited - rest)
        result = {
            "psnr_outside_cages_db": psnr,
            "pixels_outside_cages": int(outside.sum()),
            "pixels": int(outside.size),
            "max_abs_diff_outside": float(change[outside].max()),
            "head_pixels": int(head_px.sum()),
            "head_mean_rgb_change": float(change[head_px][:, :3].mean()),
            "head_mean_alpha_change": float(change[head_px][:, 3].mean()),
            "nan_pixels": int((~np.isfinite(edited)).any(axis=-1).sum()),
            "plaque_pixels": int(plaque_px.sum()),
            "plaque_min_alpha": float(edited[plaque_px][:, 3].min()) if plaque_px.any() else None,
            "frame_min_alpha": float(edited[..., 3].min()),
            "surface_vertices": len(co),
            "head_vertices": int(len(head)),
            "cage_vertices": len(rest_cage),
            "cage_tets": len(tets),
            "pinned": int(len(cage_pins(cage_object))),
            **{k: round(v, 2) for k, v in timings.items()},
        }
        from PIL import Image

        def png(name, a):
            Image.fromarray((np.clip(a, 0, 1) * 255).astype(np.uint8)).save(work / name)

        png("rest.png", rest[..., :3] ** (1 / 2.2))
        png("edited.png", edited[..., :3] ** (1 / 2.2))
        png("masks.png", np.stack([cages, head_px, plaque_px], -1).astype(float))
        return result
    finally:
        blender_nerf_deform.unregister()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--nerf", required=True, help="checkpoint trained on the fox")
    p.add_argument("--data", default=str(REPO.parent / "shared" / "datasets" / "fox"))
    p.add_argument("--downscale", type=int, default=4)
    p.add_argument("--view", type=int, default=0, help="dataset view the frame is rendered from (default 0)")
    p.add_argument("--resolution", type=int, default=192, help="extraction resolution (default 192)")
    p.add_argument("--angle", type=float, default=30.0, help="head turn in degrees (default 30)")
    p.add_argument("--cage-timeout", type=float, default=600.0, help="seconds the whole-box cage may take")
    p.add_argument("--skip-cli", action="store_true", help="only the Blender part")
    p.add_argument("--out", type=Path, default=None, help="folder for frames and masks (default: a temporary one)")
    args = p.parse_args(argv)
    work = args.out or Path(tempfile.mkdtemp(prefix="bench_edit_region_"))
    work.mkdir(parents=True, exist_ok=True)
    region = fox_region()
    region_json = work / "fox_region.json"
    region_json.write_text(json.dumps(region))
    print(f"region: {region}", flush=True)
    figures = {"region": region}
    if not args.skip_cli:
        figures["command_line"] = command_line(args, work, region_json)
    figures["blender"] = b = blender_part(args, work, region)
    print(json.dumps(figures))
    print(f"frames and masks in {work}")
    # The checks: outside both cages nothing changed, the head did move, no NaN, no hole at the cut.
    failed = [
        what
        for what, ok in (
            (f"PSNR outside the cages {b['psnr_outside_cages_db']:.1f} dB >= 45", b["psnr_outside_cages_db"] >= 45.0),
            (
                f"the head moved (mean colour change {b['head_mean_rgb_change']:.3f} > 0.02)",
                b["head_mean_rgb_change"] > 0.02,
            ),
            (f"no NaN pixel ({b['nan_pixels']})", b["nan_pixels"] == 0),
            (
                f"no hole at the cut (plaque min alpha {b['plaque_min_alpha']} >= 0.5)",
                b["plaque_min_alpha"] is not None and b["plaque_min_alpha"] >= 0.5,
            ),
        )
        if not ok
    ]
    for what in failed:
        print(f"FAILED: {what}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
