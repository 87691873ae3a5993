#!/usr/bin/env python3
"""`make demo`: the main job, end to end, on the project's embedded default scene.

    python tools/demo.py [--out demo_out] [--train-seconds 300] [--quick] ...

Stages (each prints its progress; the whole run takes about 8 minutes on 2 CPU cores):

1. scene      tools/default_scene.py builds the procedural "signpost" (a pinned base, an arm
              with a flag: the part to bend) as a .blend.
2. dataset    tools/make_dataset.py renders it with Cycles: views on a sphere, transforms.json.
3. train      `python -m blender_nerf_deform.engine train` within a time budget; the PSNR on
              held-out views is printed.
4. extension  tools/build_extension.py builds the zip; it is installed with Blender's own
              "Install from Disk" into a user folder private to the demo (your Blender setup is
              not touched) and the worker Python is set to this interpreter.
5. author     in a Blender process with the extension enabled, through the add-on's operators as an
              artist would click them: Load NeRF, Extract Mesh, Build Cage, Pin Selection (the
              base), Add Handle twice (the middle and the tip of the arm), keyframes bending the
              arm over FRAMES frames; saved as demo.blend (checkpoint path relative to it).
6. render     a fresh Blender process opens demo.blend and renders the animation through the
              "NeRF Deform" RenderEngine (what `blender -b demo.blend -a` does).
7. pictures   a GIF of the frames and a side-by-side of the first (rest) and last (bent) frame.

Everything lands in --out (default demo_out/). With the bpy module there is no `blender`
executable; the render stage is a Python process that starts like `blender -b` (preferences
read, extensions enabled) and runs Render Animation.

Children: `--child author|render CONFIG.json` runs one Blender stage in this process (the
parent starts them so that each Blender session is fresh, as on a farm).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from tools.default_scene import REGIONS  # noqa: E402  (pure data; no bpy at import)

EXTENSION_REPO = "user_default"
EXTENSION_MODULE = f"bl_ext.{EXTENSION_REPO}.blender_nerf_deform"

# The bend: the arm (from the top of the base, z = -0.5, up to z = 1.0) curls over towards -X
# (so the flag ends up pointing up) while the base stays pinned. Every handle follows the arc
# of a uniformly bent rod of the arm's length, at its own distance along the rod.
ARM_ROOT = (0.0, 0.0, -0.5)
ARM_LENGTH = 1.5
BEND_RADIANS = math.radians(80.0)
# Surface vertices (NeRF frame = world here) of each region, as boxes with a margin: the extracted
# surface lies around the true one within a grid cell or two.
SELECTION_MARGIN = 0.08
PIN_TOP = -0.42  # the base and the arm's foot up to just above the base's top (z = -0.5)
MIDDLE_BAND = (0.0, 0.25)  # a band of the arm, below the flag
TIP_BOTTOM = REGIONS["arm_tip"]["bounds"][0][2]  # the arm's top band and the flag


def bent_rod_pose(point, bend: float):
    """(location, rotation about +Y) that the uniform bend of the arm by `bend` radians gives
    to a point of the straight arm: rotation grows linearly along the rod, position follows the arc."""
    x, y, z = point
    s = z - ARM_ROOT[2]  # distance along the rod
    angle = -bend * s / ARM_LENGTH  # negative about +Y: the top goes towards -X
    if abs(bend) < 1e-9:
        return (x, y, z), 0.0
    radius = ARM_LENGTH / bend
    # The rod's centre line at s, and the point's offset from it (x) rotated with the rod.
    cx = -radius * (1.0 - math.cos(s / radius))
    cz = ARM_ROOT[2] + radius * math.sin(s / radius)
    return (cx + x * math.cos(angle), y, cz - x * math.sin(angle)), angle


# The armature rig (--rig armature): a two-bone chain up the arm, the joint at the middle handle.
ARM_JOINT_Z = 0.5 * (MIDDLE_BAND[0] + MIDDLE_BAND[1])
ARM_TOP_Z = 1.0


def rig_handles_with_bones(bpy, middle, tip, frames: int):
    """A two-bone Armature up the arm ("Lower": from the base's top to the middle handle, "Upper": on
    to the arm's top), the middle handle parented to the Lower bone and the tip handle to the Upper
    one (Blender's Parent to Bone, keeping where they are), the bones' rotations keyed from straight
    (frame 1) to the bend (frame `frames`). The bones move the handles; ARAP moves the cage between
    them and the pin, fold-free. Returns the armature object."""
    from mathutils import Matrix

    data = bpy.data.armatures.new("Arm Rig")
    rig = bpy.data.objects.new("Arm Rig", data)
    bpy.context.scene.collection.objects.link(rig)
    bpy.context.view_layer.objects.active = rig
    bpy.ops.object.mode_set(mode="EDIT")
    lower = data.edit_bones.new("Lower")
    lower.head, lower.tail = (0.0, 0.0, PIN_TOP), (0.0, 0.0, ARM_JOINT_Z)
    upper = data.edit_bones.new("Upper")
    upper.head, upper.tail = (0.0, 0.0, ARM_JOINT_Z), (0.0, 0.0, ARM_TOP_Z)
    upper.parent, upper.use_connect = lower, True
    bpy.ops.object.mode_set(mode="OBJECT")
    bpy.context.view_layer.update()
    for handle, bone in ((middle, "Lower"), (tip, "Upper")):
        world = handle.matrix_world.copy()
        handle.parent, handle.parent_type, handle.parent_bone = rig, "BONE", bone
        handle.matrix_parent_inverse = Matrix.Identity(4)
        bpy.context.view_layer.update()
        handle.matrix_world = world  # where it was: its rest is the straight arm
    # The arm's bend shared by the two joints: the top goes towards -X (negative about +Y).
    share = {"Lower": 0.45, "Upper": 0.55}
    for name, part in share.items():
        pose_bone = rig.pose.bones[name]
        pose_bone.rotation_mode = "XYZ"
        for frame, bend in ((1, 0.0), (frames, BEND_RADIANS)):
            # A vertical bone (roll 0) has its local Y along world +Z and its local Z along world -Y:
            # the bend towards -X (negative about world +Y) is positive about the bone's local Z.
            pose_bone.rotation_euler = (0.0, 0.0, bend * part)
            pose_bone.keyframe_insert("rotation_euler", frame=frame)
    return rig


# --------------------------------------------------------------------------- parent


class Stage:
    """Prints a numbered stage header and its time."""

    def __init__(self, total: int):
        self.total, self.number, self.times = total, 0, {}

    def __call__(self, name: str, what: str):
        self.number += 1
        print(f"\n[{self.number}/{self.total}] {name}: {what}", flush=True)
        self._name, self._start = name, time.monotonic()
        return self

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        elapsed = time.monotonic() - self._start
        self.times[self._name] = elapsed
        if exc[0] is None:
            print(f"    {self._name} done in {elapsed:.1f} s", flush=True)


def run(*args, env=None, capture=False) -> str:
    """Run a command with this interpreter; its output streams to the terminal (progress stays visible)."""
    command = [sys.executable, *map(str, args)]
    proc = subprocess.run(
        command,
        cwd=REPO,
        env=env,
        text=True,
        stdout=subprocess.PIPE if capture else None,
        stderr=subprocess.STDOUT if capture else None,
    )
    if proc.returncode != 0:
        tail = (proc.stdout or "")[-3000:]
        raise SystemExit(f"demo: `{' '.join(map(str, args))}` failed (exit {proc.returncode})\n{tail}")
    return proc.stdout or ""


def blender_env(user: Path) -> dict:
    # A user folder private to the demo: preferences and extensions live there, not in yours.
    return {**os.environ, "BLENDER_USER_RESOURCES": str(user)}


def install_extension(out: Path, user: Path) -> Path:
    zip_line = run("tools/build_extension.py", "--out-dir", out / "extension", capture=True).strip().splitlines()[-1]
    zip_path = Path(zip_line.split()[-1])
    if not zip_path.is_file():
        raise SystemExit(f"demo: tools/build_extension.py printed {zip_line!r}, not a zip path")
    script = f"""
import bpy
result = bpy.ops.extensions.package_install_files(filepath={str(zip_path)!r}, repo={EXTENSION_REPO!r},
                                                  enable_on_install=True)
assert result == {{"FINISHED"}}, result
prefs = bpy.context.preferences.addons[{EXTENSION_MODULE!r}].preferences
prefs.worker_python = {sys.executable!r}
bpy.ops.wm.save_userpref()
print("installed", {str(zip_path)!r})
"""
    run("-c", script, env=blender_env(user))
    return zip_path


def save_gif_and_side_by_side(frames: list[Path], gif: Path, side: Path, background=(38, 38, 42)) -> None:
    from PIL import Image, ImageDraw

    def on_background(path):
        image = Image.open(path).convert("RGBA")
        canvas = Image.new("RGBA", image.size, background + (255,))
        return Image.alpha_composite(canvas, image).convert("RGB")

    pictures = [on_background(p) for p in frames]
    # Forth and back, so that the loop has no jump.
    loop = pictures + pictures[-2:0:-1]
    from blender_nerf_deform.engine.files import atomic_write

    atomic_write(
        gif,
        lambda f: loop[0].save(
            f, format="GIF", save_all=True, append_images=loop[1:], duration=1000 // 24, loop=0, optimize=True
        ),
    )
    first, last = pictures[0], pictures[-1]
    w, h = first.size
    label = max(14, h // 12)
    canvas = Image.new("RGB", (2 * w, h + label + 8), background)
    canvas.paste(first, (0, label + 8))
    canvas.paste(last, (w, label + 8))
    draw = ImageDraw.Draw(canvas)
    draw.text((6, 4), "original", fill=(235, 235, 235))
    draw.text((w + 6, 4), "deformed", fill=(235, 235, 235))
    atomic_write(side, lambda f: canvas.save(f, format="PNG"))


def parse_args(argv):
    p = argparse.ArgumentParser(
        prog="demo.py", description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--out", type=Path, default=REPO / "demo_out", help="output folder (default demo_out/)")
    p.add_argument("--train-seconds", type=float, default=300.0, help="NeRF training budget (default 300)")
    p.add_argument(
        "--train-steps",
        type=int,
        default=0,
        help="train for this many steps instead of a time budget (the same NeRF on a busy machine)",
    )
    p.add_argument("--views", type=int, default=100, help="training views (default 100)")
    p.add_argument("--image-size", type=int, default=200, help="training image size in pixels (default 200)")
    p.add_argument("--extract-resolution", type=int, default=256, help="extraction grid per axis (default 256)")
    p.add_argument("--render-size", type=int, default=320, help="rendered frame size in pixels (default 320)")
    p.add_argument("--frames", type=int, default=24, help="frames of the bend animation (default 24)")
    p.add_argument(
        "--rig",
        choices=("handles", "armature"),
        default="handles",
        help="what animates the bend: the handles' own keyframes (default), or a two-bone armature the "
        "handles are parented to (bones keyed, ARAP in between)",
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help="a reduced run for tests: 40 views of 64 px, 400 training steps, 96^3 extraction, 6 frames of 64 px",
    )
    p.add_argument("--child", choices=("author", "render"), help=argparse.SUPPRESS)
    p.add_argument("config", nargs="?", type=Path, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.quick:
        # Steps, not seconds: a time budget trains a worse NeRF on a loaded machine (a CI run beside
        # other work got 182 steps in 45 s and an arm too faint to extract; an idle one about 400).
        args.train_steps = args.train_steps or 400
        args.views, args.image_size = 40, 64
        args.extract_resolution, args.render_size, args.frames = 96, 64, 6
    for name in ("train_seconds", "views", "image_size", "extract_resolution", "render_size"):
        if not getattr(args, name) > 0:
            p.error(f"--{name.replace('_', '-')} must be positive, got {getattr(args, name)}")
    if args.train_steps < 0:
        p.error(f"--train-steps must not be negative, got {args.train_steps}")
    if args.frames < 2:
        p.error(f"--frames must be at least 2 (a rest frame and a bent one), got {args.frames}")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.child:
        return {"author": author, "render": render}[args.child](json.loads(args.config.read_text()))

    out = args.out.resolve()
    if out.exists() and not out.is_dir():
        raise SystemExit(f"demo: --out {out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    user = out / "blender_user"
    # One numba kernel cache for every process of the demo (copies of the same engine share it,
    # engine/kernel_cache.py): the installed extension's worker loads the frame kernels the training
    # compiled (a few seconds; it still compiles the bending and point-location kernels once), and all of
    # them stay for the next demo. The test suite uses the same folder.
    os.environ.setdefault("NUMBA_CACHE_DIR", str(REPO / "build" / "numba_cache"))
    started = time.monotonic()
    stage = Stage(7)

    with stage("scene", "build the procedural default scene"):
        run("tools/default_scene.py", "--out", out / "scene.blend")

    dataset = out / "dataset"
    with stage("dataset", f"render {args.views} training views of {args.image_size} px with Cycles"):
        run(
            "tools/make_dataset.py",
            "--blend",
            out / "scene.blend",
            "--out",
            dataset,
            "--count",
            args.views,
            "--test-count",
            8,
            "--resolution",
            args.image_size,
            "--radius",
            4.0,
            "--samples",
            16,
            "--seed",
            0,
        )

    run_dir = out / "run"
    budget = ("--steps", args.train_steps) if args.train_steps else ("--max-seconds", args.train_seconds)
    with stage(
        "train",
        f"train the NeRF for {args.train_steps} steps"
        if args.train_steps
        else f"train the NeRF for {args.train_seconds:g} s",
    ):
        run(
            "-m", "blender_nerf_deform.engine", "train", "--data", dataset, "--out", run_dir, *budget, "--overwrite"
        )  # a rerun of the demo trains anew
        psnr = run(
            "-m",
            "blender_nerf_deform.engine",
            "eval",
            "--nerf",
            run_dir / "nerf.ckpt",
            "--data",
            dataset / "test",
            capture=True,
        )
        print("    held-out views:", psnr.strip().splitlines()[-1], flush=True)

    with stage("extension", "build the extension and install it (a Blender user folder private to the demo)"):
        zip_path = install_extension(out, user)

    blend = out / "demo.blend"
    config = {
        "out": str(out),
        "blend": str(blend),
        "checkpoint": str(run_dir / "nerf.ckpt"),
        "extract_resolution": args.extract_resolution,
        "render_size": args.render_size,
        "frames": args.frames,
        "rig": args.rig,
    }
    config_path = out / "demo_config.json"
    config_path.write_text(json.dumps(config, indent=1))
    with stage("author", "Load NeRF, Extract Mesh, Build Cage, pin the base, two handles, keyframes -> demo.blend"):
        run("tools/demo.py", "--child", "author", config_path, env=blender_env(user))

    with stage("render", f"render frames 1-{args.frames} headless through the NeRF Deform RenderEngine"):
        run("tools/demo.py", "--child", "render", config_path, env=blender_env(user))
    frames = sorted((out / "frames").glob("frame_*.png"))
    if len(frames) != args.frames:
        raise SystemExit(f"demo: expected {args.frames} frames in {out / 'frames'}, found {len(frames)}")

    gif, side = out / "demo.gif", out / "side_by_side.png"
    with stage("pictures", "GIF and side-by-side"):
        save_gif_and_side_by_side(frames, gif, side)

    total = time.monotonic() - started
    print(f"\nmake demo: done in {total / 60:.1f} min ({', '.join(f'{k} {v:.0f} s' for k, v in stage.times.items())})")
    print(f"  blend file   {blend}   (open it in Blender with the extension: {zip_path})")
    print(f"  frames       {out / 'frames'}/frame_0001.png .. frame_{args.frames:04d}.png")
    print(f"  GIF          {gif}")
    print(f"  side by side {side}")
    print(f"  NeRF         {run_dir / 'nerf.ckpt'}   dataset {dataset}")
    print(f"  with Blender installed: blender -b {blend} -a   renders the same frames")
    return 0


# --------------------------------------------------------------------------- children (bpy)


def _start_blender():
    """As `blender -b` starts: the user preferences read, so the installed extension is enabled."""
    import bpy

    bpy.ops.wm.read_userpref()
    if not hasattr(bpy.types.Object, "nerf_deform"):
        raise SystemExit(
            f"demo: the extension {EXTENSION_MODULE} is not enabled in {os.environ.get('BLENDER_USER_RESOURCES')}"
        )
    return bpy


def _check(result, what: str) -> None:
    if result != {"FINISHED"}:
        raise SystemExit(f"demo: {what} returned {result}; see the report above")


def _select_vertices(bpy, surface, mask) -> int:
    """Select exactly the vertices in `mask` on the surface in Edit Mode, as an artist would."""
    import bmesh

    bpy.context.view_layer.objects.active = surface
    if surface.mode != "EDIT":
        bpy.ops.object.mode_set(mode="EDIT")
    # Through bmesh, not Mesh.edges.foreach_set("select"): on a mesh built in bulk (no selection
    # attributes yet) the latter crashes Blender 5.0.1.
    bm = bmesh.from_edit_mesh(surface.data)
    bm.select_mode = {"VERT"}
    for element in (*bm.edges, *bm.faces):
        element.select = False
    for vert, flag in zip(bm.verts, mask.tolist()):
        vert.select = flag
    bmesh.update_edit_mesh(surface.data)
    return int(mask.sum())


def author(config: dict) -> int:
    import numpy as np

    bpy = _start_blender()
    from mathutils import Matrix, Vector

    blend = config["blend"]
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    # Saved first, so the checkpoint path is stored relative to the .blend.
    bpy.ops.wm.save_as_mainfile(filepath=blend)
    _check(bpy.ops.nerf_deform.load_nerf(filepath=config["checkpoint"]), "Load NeRF")
    nerf = bpy.context.active_object
    nerf.nerf_deform.resolution = config["extract_resolution"]
    _check(bpy.ops.nerf_deform.extract_mesh(), "Extract Mesh")
    surface = nerf.nerf_deform.surface
    bpy.context.view_layer.objects.active = nerf
    _check(bpy.ops.nerf_deform.build_cage(), "Build Cage")

    co = np.empty(3 * len(surface.data.vertices), dtype=np.float32)
    surface.data.vertices.foreach_get("co", co)
    x, y, z = co.reshape(-1, 3).T  # the NeRF object sits at the origin: its frame is the world's
    m = SELECTION_MARGIN
    (ax0, ay0, _), (ax1, ay1, _) = REGIONS["arm"]["bounds"]
    in_arm_column = (x > -0.2 - m) & (x < 0.2 + m) & (y > ay0 - m) & (y < ay1 + m)
    regions = {
        "pin": z < PIN_TOP,
        "Middle": in_arm_column & (z > MIDDLE_BAND[0]) & (z < MIDDLE_BAND[1]),
        "Tip": (x > ax0 - m) & (x < ax1 + m) & (y > ay0 - m) & (y < ay1 + m) & (z > TIP_BOTTOM),
    }
    print(
        f"    {len(co) // 3} surface vertices; pinned {int(regions['pin'].sum())}, middle handle "
        f"{int(regions['Middle'].sum())}, tip handle {int(regions['Tip'].sum())}",
        flush=True,
    )

    _select_vertices(bpy, surface, regions["pin"])
    _check(bpy.ops.nerf_deform.pin_selection(), "Pin Selection")
    frames = config["frames"]
    handles = {}
    for name in ("Middle", "Tip"):
        _select_vertices(bpy, surface, regions[name])
        _check(bpy.ops.nerf_deform.add_handle(), f"Add Handle ({name})")
        handles[name] = handle = bpy.context.active_object
        handle.name = f"{name} Handle"
        if config.get("rig", "handles") != "handles":
            continue
        rest = tuple(handle.location)
        for frame, bend in ((1, 0.0), (frames, BEND_RADIANS)):
            location, angle = bent_rod_pose(rest, bend)
            handle.location = location
            handle.rotation_euler = (0.0, angle, 0.0)
            handle.keyframe_insert("location", frame=frame)
            handle.keyframe_insert("rotation_euler", frame=frame)
    bpy.ops.object.mode_set(mode="OBJECT")
    if config.get("rig") == "armature":
        rig = rig_handles_with_bones(bpy, handles["Middle"], handles["Tip"], frames)
        print(
            f"    armature {rig.name}: bones {', '.join(b.name for b in rig.data.bones)} keyed; "
            "the handles follow them",
            flush=True,
        )

    # The camera of the default scene, a little further out so the bent arm stays in frame.
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(cam)
    target = Vector((-0.25, 0.0, 0.05))
    position = target + Vector((2.6, -2.9, 1.3)) * 1.1
    cam.matrix_world = Matrix.Translation(position) @ (target - position).to_track_quat("-Z", "Y").to_matrix().to_4x4()
    cam.data.lens, cam.data.sensor_width = 50.0, 36.0
    scene.camera = cam

    render = scene.render
    render.resolution_x = render.resolution_y = config["render_size"]
    render.resolution_percentage = 100
    render.image_settings.file_format = "PNG"
    render.image_settings.color_mode = "RGBA"
    render.filepath = "//frames/frame_"
    scene.frame_start, scene.frame_end = 1, frames
    scene.render.fps = 24
    scene.frame_set(1)
    bpy.ops.wm.save_as_mainfile(filepath=blend)

    # The render camera in transforms.json form: `engine render --cameras` takes it, and the
    # tests project the scene's regions with it.
    from tools.make_dataset import intrinsics, write_json_atomic

    c2w = [list(row) for row in cam.matrix_world]
    write_json_atomic(
        Path(config["out"]) / "cameras.json",
        {
            **intrinsics(scene, cam),
            "frames": [
                {"file_path": f"frames/frame_{f:04d}.png", "transform_matrix": c2w} for f in range(1, frames + 1)
            ],
        },
    )
    print(
        f"    wrote {blend} (engine {render.engine}, frames 1-{frames}, checkpoint {nerf.nerf_deform.checkpoint})",
        flush=True,
    )
    return 0


def render(config: dict) -> int:
    bpy = _start_blender()
    bpy.ops.wm.open_mainfile(filepath=config["blend"])
    scene = bpy.context.scene
    count = scene.frame_end - scene.frame_start + 1

    @bpy.app.handlers.persistent
    def report(scene_, *_):
        done = scene_.frame_current - scene.frame_start + 1
        print(
            f"    frame {scene_.frame_current} ({done}/{count}) -> {bpy.path.abspath(scene_.render.frame_path())}",
            flush=True,
        )

    bpy.app.handlers.render_write.append(report)
    _check(bpy.ops.render.render(animation=True), "Render Animation")
    return 0


if __name__ == "__main__":
    from blender_nerf_deform.engine.errors import run_command  # an error nobody foresaw: one line naming its log

    raise SystemExit(run_command("demo.py", main))
