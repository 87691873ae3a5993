#!/usr/bin/env python3
"""Smoke of the built extension zip in several Blender releases (their bpy wheels), as an artist does.

    python tools/smoke_blender.py --release 4.2=.smoke/bpy-4.2/bin/python --release 5.0=.venv/bin/python ...

`make smoke` makes one virtual environment per release (pins in addon_tests/smoke/) and runs this
with the project's .venv Python, which also runs the worker. The script builds the zip once (or
takes --zip), trains a tiny NeRF once (an analytic sphere, a few hundred steps on the CPU, or
takes --nerf), then for each release, one after the other, each step in its own process of that
release's Python (user preferences in a temporary BLENDER_USER_RESOURCES, never the developer's):

  validate  Blender's own blender_ext.py of that release validates the zip's manifest
  author    install the zip as an extension (enabled on install), save the preferences, draw the
            add-on's panels and its preferences, Load NeRF, Extract Mesh, Build Cage, a handle
            (moved), draw the panels again, one F12 frame through the worker, save the .blend
  reopen    enable the extension as `blender -b` does (the saved preferences), open the .blend,
            render the same frame again, disable the extension: nothing of it stays registered

A step passes when its process exits 0 with no sign of a crash in its output (a segfault, a heap
error, Blender's leak report, a Python traceback) and left no process behind (the worker ends
with Blender). One that does not finish in --timeout seconds, or that finished its script but
does not exit within --exit-grace seconds (a hang in Blender's teardown), is killed and fails.
The two frames must agree. Prints one line per release and ends with `N passed, M failed`;
exits 1 when a release failed.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
EXT_ID = "blender_nerf_deform"
MODULE = f"bl_ext.user_default.{EXT_ID}"
DONE = "SMOKE-STEP-DONE"
# What glibc, Blender's guarded allocator and Python print when memory or code went wrong
# (addon_tests/fixtures/processes.py CRASH_SIGNS, plus Blender's note of memory freed after exit).
CRASH_SIGNS = (
    "corrupted",
    "free():",
    "double free",
    "munmap_chunk",
    "malloc():",
    "Not freed memory blocks",
    "Segmentation fault",
    "Traceback (most recent call last)",
    "Freeing memory after the leak detector",
)
RENDER_SIZE = 32
EXTRACT_RESOLUTION = 32
THRESHOLD = 10.0  # the add-on's default density threshold


# --------------------------------------------------------------------------- the tiny NeRF


def write_sphere_dataset(folder: Path, views: int = 16, size: int = 32) -> Path:
    """An analytic dataset: a sphere of radius 0.8 coloured by its normal, ray-cast from cameras on a
    sphere of radius 3 (Blender/OpenGL convention, NeRF-synthetic form, RGBA with straight alpha)."""
    import numpy as np
    from PIL import Image

    (folder / "images").mkdir(parents=True, exist_ok=True)
    angle, radius, ss = 0.9, 0.8, 2
    f = 0.5 * size / math.tan(0.5 * angle)
    frames = []
    for k in range(views):
        zc = 1 - 2 * (k + 0.5) / views
        phi = k * math.pi * (3 - math.sqrt(5))
        eye = 3.0 * np.array([math.sqrt(1 - zc * zc) * math.cos(phi), math.sqrt(1 - zc * zc) * math.sin(phi), zc])
        z = eye / np.linalg.norm(eye)
        x = np.cross((0.0, 0.0, 1.0), z)
        x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-8 else np.array([1.0, 0.0, 0.0])
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, np.cross(z, x), z, eye
        sub = (np.arange(size * ss) + 0.5) / ss
        jj, ii = np.meshgrid(sub, sub, indexing="ij")
        d = np.stack([(ii - size / 2) / f, -(jj - size / 2) / f, -np.ones_like(ii)], -1) @ c2w[:3, :3].T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        b = d @ eye
        disc = b * b - (eye @ eye - radius**2)
        hit = disc > 0
        p = eye + d * (-b - np.sqrt(np.maximum(disc, 0)))[..., None]
        a = hit.astype(np.float64)
        rgb = np.where(hit[..., None], 0.5 + 0.5 * p / radius, 0.0)
        pre = np.concatenate([rgb * a[..., None], a[..., None]], -1).reshape(size, ss, size, ss, 4).mean((1, 3))
        alpha = pre[..., 3:]
        rgba = np.concatenate([np.where(alpha > 0, pre[..., :3] / np.maximum(alpha, 1e-9), 0), alpha], -1)
        Image.fromarray((np.clip(rgba, 0, 1) * 255 + 0.5).astype(np.uint8), "RGBA").save(
            folder / "images" / f"r_{k}.png"
        )
        frames.append({"file_path": f"images/r_{k}", "transform_matrix": c2w.tolist()})
    (folder / "transforms.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    return folder


def train_nerf(root: Path, worker_python: str, steps: int, env: dict) -> Path:
    data = write_sphere_dataset(root / "data")
    run = root / "run"
    proc = subprocess.run(
        [
            worker_python,
            "-m",
            "blender_nerf_deform.engine",
            "train",
            "--data",
            str(data),
            "--out",
            str(run),
            "--steps",
            str(steps),
            "--device",
            "cpu",
        ],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    if proc.returncode != 0 or not (run / "nerf.ckpt").is_file():
        raise SystemExit(f"smoke: training the tiny NeRF failed (exit {proc.returncode}):\n{proc.stderr[-3000:]}")
    return run / "nerf.ckpt"


# --------------------------------------------------------------------------- one step in one process


def _session_alive(sid: int) -> list[int]:
    """Processes still in session `sid` (the step's Blender and whatever it started)."""
    alive = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if os.getsid(int(entry.name)) == sid:
                    alive.append(int(entry.name))
            except (ProcessLookupError, PermissionError):
                pass
    return alive


def _kill_session(sid: int) -> None:
    for pid in [sid, *_session_alive(sid)]:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def run_step(
    python: str, args: list[str], log: Path, env: dict, timeout: float, exit_grace: float
) -> tuple[bool, str, float]:
    """Run `python args...` in a new session, output into `log`; (passed, why not, seconds)."""
    started = time.monotonic()
    with log.open("w") as out:
        proc = subprocess.Popen(
            [python, *args],
            cwd=REPO,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
        )
    done_at, problem = None, ""
    while proc.poll() is None:
        time.sleep(0.2)
        now = time.monotonic()
        if done_at is None and DONE in log.read_text(errors="replace"):
            done_at = now
        if done_at is not None and now - done_at > exit_grace:
            problem = (
                f"finished its script but did not exit within {exit_grace:.0f} s (a hang in Blender's teardown): killed"
            )
        elif now - started > timeout:
            problem = f"no exit within {timeout:.0f} s: killed (hung?)"
        if problem:
            _kill_session(proc.pid)
            proc.wait()
            break
    seconds = time.monotonic() - started
    output = log.read_text(errors="replace")
    if not problem:
        if proc.returncode != 0:
            name = f" ({signal.Signals(-proc.returncode).name})" if proc.returncode < 0 else ""
            problem = f"exit {proc.returncode}{name}" + (" (139: segfault)" if proc.returncode == 139 else "")
        elif DONE not in output:
            problem = "exited 0 before the end of its script"
        elif signs := [s for s in CRASH_SIGNS if s in output]:
            problem = f"exit 0 but its output shows {signs}"
    # The worker (and anything else Blender started) must end with it.
    deadline = time.monotonic() + 15
    while (left := _session_alive(proc.pid)) and time.monotonic() < deadline:
        time.sleep(0.2)
    if left:
        _kill_session(proc.pid)
        problem = problem or f"left {len(left)} process(es) running after it exited (killed)"
    return not problem, problem, seconds


def compare_frames(a: Path, b: Path) -> str:
    """'' when both frames exist, show the NeRF and agree; else what is wrong."""
    import numpy as np
    from PIL import Image

    for path in (a, b):
        if not path.is_file():
            return f"no frame {path.name}"
    x = np.asarray(Image.open(a).convert("RGBA"), dtype=np.int16)
    y = np.asarray(Image.open(b).convert("RGBA"), dtype=np.int16)
    covered = int((x[..., 3] > 128).sum())
    if covered < 0.05 * x.shape[0] * x.shape[1]:
        return f"the first frame shows almost no NeRF ({covered} opaque pixels)"
    diff = int(np.abs(x - y).max()) if x.shape == y.shape else -1
    return "" if 0 <= diff <= 3 else f"the reopened file's frame differs from the first (max difference {diff}/255)"


def smoke_release(
    label: str, python: str, zip_path: Path, nerf: Path, root: Path, base_env: dict, args
) -> tuple[bool, str]:
    work = root / label
    project = work / "project"
    (project / "run").mkdir(parents=True)
    shutil.copy2(nerf, project / "run" / "nerf.ckpt")
    config = {
        "zip": str(zip_path),
        "blend": str(project / "shot.blend"),
        "checkpoint": str(project / "run" / "nerf.ckpt"),
        "frame_a": str(project / "frame_a.png"),
        "frame_b": str(project / "frame_b.png"),
    }
    (work / "config.json").write_text(json.dumps(config))
    env = {**base_env, "BLENDER_USER_RESOURCES": str(work / "user")}
    times = []
    steps = [
        ("validate", ["-c", VALIDATE, str(zip_path)]),
        ("author", [__file__, "--child", "author", str(work / "config.json")]),
        ("reopen", [__file__, "--child", "reopen", str(work / "config.json")]),
    ]
    for name, step_args in steps:
        log = work / f"{name}.log"
        ok, problem, seconds = run_step(python, step_args, log, env, args.timeout, args.exit_grace)
        times.append(f"{name} {seconds:.0f} s")
        if not ok:
            tail = "\n".join("      " + line for line in log.read_text(errors="replace").splitlines()[-25:])
            return False, f"{name}: {problem} ({log})\n{tail}"
        if name == "reopen" and (problem := compare_frames(Path(config["frame_a"]), Path(config["frame_b"]))):
            return False, f"reopen: {problem}"
    version = (work / "version.txt").read_text().strip() if (work / "version.txt").is_file() else "?"
    return True, f"bpy {version}: " + ", ".join(times)


# The manifest is checked by the release's own tool (shipped in its bpy module), on the built zip.
VALIDATE = """
import glob, importlib.util, os, subprocess, sys
bpy_dir = next(iter(importlib.util.find_spec("bpy").submodule_search_locations))
tool = sorted(glob.glob(os.path.join(bpy_dir, "*", "scripts", "addons_core", "bl_pkg", "cli", "blender_ext.py")))
assert tool, "no blender_ext.py in this bpy"
proc = subprocess.run([sys.executable, tool[-1], "validate", sys.argv[1]], capture_output=True, text=True)
print(proc.stdout + proc.stderr)
assert proc.returncode == 0, "blender_ext.py validate failed"
print("SMOKE-STEP-DONE validate")
"""


# --------------------------------------------------------------------------- inside a release's Python (bpy)


def _ui_checker(bpy):
    """A stand-in for UILayout that checks every call a panel makes against this release's UILayout:
    the function exists, its keyword arguments are parameters of it, icons and enum values exist,
    properties and operators named exist. Returns (layout factory, list of problems)."""
    rna = bpy.types.UILayout.bl_rna
    functions = rna.functions
    icons = set(functions["label"].parameters["icon"].enum_items.keys())
    problems: list[str] = []

    class OperatorProps:
        def __init__(self, idname, rna_type):
            object.__setattr__(self, "_where", (idname, rna_type))

        def __setattr__(self, name, value):
            idname, rna_type = self._where
            if rna_type is not None and name not in rna_type.properties:
                problems.append(f"operator {idname} has no property {name!r}")

    class Layout:
        def __setattr__(self, name, value):
            if name not in rna.properties:
                problems.append(f"UILayout has no attribute {name!r}")

        def __getattr__(self, name):
            if name in rna.properties:
                return getattr(type(self), "_defaults", {}).get(name, None)
            if name not in functions:
                problems.append(f"UILayout has no function {name!r}")
                return lambda *a, **k: Layout()
            params = functions[name].parameters

            def call(*args, **kwargs):
                for key, value in kwargs.items():
                    if key not in params:
                        problems.append(f"UILayout.{name}() has no parameter {key!r}")
                    elif key == "icon" and value not in icons:
                        problems.append(f"icon {value!r} does not exist in this release")
                if name == "prop":
                    data = args[0] if args else kwargs.get("data")
                    prop = args[1] if len(args) > 1 else kwargs.get("property")
                    if prop not in data.bl_rna.properties:
                        problems.append(f"{type(data).__name__} has no property {prop!r}")
                if name == "operator":
                    idname = args[0]
                    try:
                        mod, op = idname.split(".")
                        rna_type = getattr(getattr(bpy.ops, mod), op).get_rna_type()
                    except (AttributeError, KeyError, ValueError, RuntimeError):
                        problems.append(f"operator {idname!r} does not exist")
                        rna_type = None
                    return OperatorProps(idname, rna_type)
                return (
                    Layout()
                    if functions[name].parameters.get("layout") is not None
                    or name in ("row", "column", "box", "split", "grid_flow", "column_flow")
                    else None
                )

            return call

    return Layout, problems


def draw_everything(bpy, where: str) -> int:
    """Poll and draw each panel of the add-on and its preferences with the checking layout; the
    number of panels drawn. A problem raises AssertionError naming it."""
    Layout, problems = _ui_checker(bpy)

    class Self:
        def __init__(self, target):
            object.__setattr__(self, "_target", target)
            object.__setattr__(self, "layout", Layout())

        def __getattr__(self, name):
            return getattr(self._target, name)

    drawn = 0
    panels = [cls for cls in bpy.types.Panel.__subclasses__() if EXT_ID in cls.__module__ and cls.is_registered]
    assert panels, "no panel of the add-on is registered"
    for cls in panels:
        if hasattr(cls, "poll") and not cls.poll(bpy.context):
            continue
        cls.draw(Self(cls), bpy.context)
        drawn += 1
    prefs = bpy.context.preferences.addons[MODULE].preferences
    type(prefs).draw(Self(prefs), bpy.context)
    assert not problems, f"drawing the panels ({where}): " + "; ".join(sorted(set(problems)))
    print(f"  drew {drawn} of {len(panels)} panels and the preferences ({where})", flush=True)
    return drawn


_STARTED = time.monotonic()


def _check(result, what):
    assert result == {"FINISHED"}, f"{what} returned {result}"
    print(f"  {what}: done ({time.monotonic() - _STARTED:.1f} s)", flush=True)


def _nothing_registered(bpy) -> list[str]:
    left = [name for name in dir(bpy.types) if name.startswith(("NERFDEFORM_", "NERF_DEFORM_"))]
    if hasattr(bpy.types.Object, "nerf_deform"):
        left.append("Object.nerf_deform")
    for name in dir(bpy.app.handlers):
        handlers = getattr(bpy.app.handlers, name)
        if isinstance(handlers, list):
            left += [f"handler {name}.{fn.__name__}" for fn in handlers if EXT_ID in getattr(fn, "__module__", "")]
    if MODULE in bpy.context.preferences.addons.keys():
        left.append(f"{MODULE} still enabled")
    return left


def _render(bpy, path: str):
    scene = bpy.context.scene
    scene.render.filepath = path
    _check(bpy.ops.render.render(write_still=True), f"F12 ({scene.render.engine}, {path.rsplit('/', 1)[-1]})")


def child_author(config: dict) -> None:
    import bpy

    import bmesh  # (after bpy, which makes it importable)
    import numpy as np
    from mathutils import Vector

    print(f"Blender {bpy.app.version_string}", flush=True)
    Path(config["blend"]).parent.parent.joinpath("version.txt").write_text(bpy.app.version_string)
    _check(
        bpy.ops.extensions.package_install_files(filepath=config["zip"], repo="user_default", enable_on_install=True),
        "install the zip",
    )
    assert MODULE in bpy.context.preferences.addons.keys(), f"{MODULE} is not enabled after install"
    assert sys.modules[MODULE].__package__ == MODULE
    _check(bpy.ops.wm.save_userpref(), "save the preferences")
    draw_everything(bpy, "no NeRF")

    for obj in list(bpy.data.objects):  # the startup scene's cube, light and camera
        bpy.data.objects.remove(obj)
    _check(bpy.ops.wm.save_as_mainfile(filepath=config["blend"]), "save (so the checkpoint goes relative)")
    _check(bpy.ops.nerf_deform.load_nerf(filepath=config["checkpoint"]), "Load NeRF")
    nerf = bpy.context.active_object
    assert nerf.nerf_deform.checkpoint.startswith("//"), nerf.nerf_deform.checkpoint
    nerf.nerf_deform.resolution, nerf.nerf_deform.threshold = EXTRACT_RESOLUTION, THRESHOLD
    _check(bpy.ops.nerf_deform.extract_mesh(), "Extract Mesh")
    surface = nerf.nerf_deform.surface
    bpy.context.view_layer.objects.active = nerf
    _check(bpy.ops.nerf_deform.build_cage(), "Build Cage")

    co = np.empty(3 * len(surface.data.vertices), dtype=np.float32)
    surface.data.vertices.foreach_get("co", co)
    z = co.reshape(-1, 3)[:, 2]
    top = z > np.quantile(z, 0.8)  # the mesh's top fifth
    assert top.any() and not top.all(), f"{int(top.sum())} of {len(top)} vertices in the top fifth"
    bpy.context.view_layer.objects.active = surface
    bpy.ops.object.mode_set(mode="EDIT")
    bm = bmesh.from_edit_mesh(surface.data)
    bm.select_mode = {"VERT"}
    for element in (*bm.edges, *bm.faces):
        element.select = False
    for vert, flag in zip(bm.verts, top.tolist()):
        vert.select = flag
    bmesh.update_edit_mesh(surface.data)
    _check(bpy.ops.nerf_deform.add_handle(), f"Add Handle ({int(top.sum())} vertices)")
    handle = bpy.context.active_object
    bpy.ops.object.mode_set(mode="OBJECT")
    handle.location.z += 0.25
    bpy.context.view_layer.objects.active = nerf
    draw_everything(bpy, "a NeRF with its mesh, cage and a handle")

    scene = bpy.context.scene
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(cam)
    scene.camera = cam
    cam.location = (0.0, -3.2, 0.8)
    cam.rotation_euler = (-Vector(cam.location)).to_track_quat("-Z", "Y").to_euler()
    cam.data.sensor_fit, cam.data.angle_x = "HORIZONTAL", 0.9
    scene.render.resolution_x = scene.render.resolution_y = RENDER_SIZE
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format, scene.render.image_settings.color_mode = "PNG", "RGBA"
    assert scene.render.engine == "NERF_DEFORM", scene.render.engine
    _render(bpy, config["frame_a"])
    _check(bpy.ops.wm.save_as_mainfile(filepath=config["blend"]), "save the .blend")
    print(DONE, "author", flush=True)


def child_reopen(config: dict) -> None:
    import bpy

    print(f"Blender {bpy.app.version_string}", flush=True)
    if bpy.app.version >= (4, 3, 0):
        # As `blender -b` starts: the saved preferences enable the extension.
        _check(bpy.ops.wm.read_userpref(), "read the saved preferences")
    else:
        # The bpy module of 4.2 LTS crashes in wm.read_userpref() with or without any add-on
        # (UI_icons_reload_internal_textures makes a GPU texture with no GPU context), which
        # `blender -b` never calls: enable the installed extension as the preferences would.
        _check(bpy.ops.preferences.addon_enable(module=MODULE), "enable the installed extension")
    assert hasattr(bpy.types.Object, "nerf_deform"), "NeRF Deform is not enabled"
    _check(bpy.ops.wm.open_mainfile(filepath=config["blend"]), "open the .blend")
    scene = bpy.context.scene
    assert scene.render.engine == "NERF_DEFORM", scene.render.engine
    _render(bpy, config["frame_b"])
    _check(bpy.ops.preferences.addon_disable(module=MODULE), "disable the extension")
    left = _nothing_registered(bpy)
    assert not left, f"still registered after disabling: {left}"
    print(DONE, "reopen", flush=True)


# --------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--release",
        action="append",
        default=[],
        metavar="LABEL=PYTHON",
        help="a release to smoke: its label and a Python that has its bpy wheel (repeat)",
    )
    parser.add_argument(
        "--worker-python", default=sys.executable, help="the worker's Python, with torch (default: this one)"
    )
    parser.add_argument("--zip", type=Path, help="the extension zip (default: built now with tools/build_extension.py)")
    parser.add_argument("--nerf", type=Path, help="a NeRF checkpoint (default: a tiny one trained now)")
    parser.add_argument(
        "--steps",
        type=int,
        default=200,
        help="training steps of the tiny NeRF (default 200: its density peaks near 60, the threshold is 10)",
    )
    parser.add_argument("--timeout", type=float, default=300, help="seconds one step's process may run (default 300)")
    parser.add_argument(
        "--exit-grace",
        type=float,
        default=60,
        help="seconds a process may take to exit once its script finished (default 60)",
    )
    parser.add_argument(
        "--work-dir", type=Path, help="keep everything here (default: a temporary folder, removed on success)"
    )
    parser.add_argument("--child", nargs=2, metavar=("STEP", "CONFIG"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)

    if args.child:
        step, config = args.child
        {"author": child_author, "reopen": child_reopen}[step](json.loads(Path(config).read_text()))
        return 0
    if not args.release:
        parser.error("give at least one --release LABEL=PYTHON")
    releases = []
    for item in args.release:
        label, sep, python = item.partition("=")
        if not sep or not label or not python:
            parser.error(f"--release {item!r}: expected LABEL=PYTHON")
        if shutil.which(python) is None and not Path(python).is_file():
            parser.error(f"--release {item!r}: no Python {python}")
        releases.append((label, python))

    root = args.work_dir or Path(tempfile.mkdtemp(prefix="nerf_deform_smoke_"))
    root.mkdir(parents=True, exist_ok=True)
    worker = str(Path(args.worker_python).absolute())
    env = {
        k: v for k, v in os.environ.items() if not k.startswith("BLENDER_") and k not in ("PYTHONPATH", "PYTHONHOME")
    }
    env["NERF_DEFORM_PYTHON"] = worker
    # One numba kernel cache for the run: the workers of every release (the same worker Python, each with
    # its own installed copy of the engine) load the kernels the first one compiled (engine/kernel_cache.py).
    env.setdefault("NUMBA_CACHE_DIR", str(root / "numba_cache"))
    started = time.monotonic()
    if args.zip is None:
        sys.path.insert(0, str(REPO))
        from tools.build_extension import build

        zip_path = build(root / "dist")
    else:
        zip_path = args.zip.absolute()
    if args.nerf is None:
        t = time.monotonic()
        nerf = train_nerf(root / "nerf", worker, args.steps, env)
        print(f"smoke: tiny NeRF trained in {time.monotonic() - t:.0f} s ({args.steps} steps)", flush=True)
    else:
        nerf = args.nerf.absolute()
    print(f"smoke: {zip_path.name}, worker {worker}, work in {root}", flush=True)

    passed = failed = 0
    for label, python in releases:
        t = time.monotonic()
        ok, note = smoke_release(label, python, zip_path, nerf, root, env, args)
        passed, failed = passed + ok, failed + (not ok)
        print(f"{label}: {'passed' if ok else 'FAILED'} in {time.monotonic() - t:.0f} s  {note}", flush=True)
    print(f"smoke: {len(releases)} releases in {time.monotonic() - started:.0f} s")
    if failed == 0 and args.work_dir is None:
        shutil.rmtree(root, ignore_errors=True)
    print(f"{passed} passed, {failed} failed")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
