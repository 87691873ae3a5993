"""Batch rendering as a render farm does it: fresh processes, the extension enabled from saved
preferences (as `blender -b` starts), the .blend alone (plus its checkpoint) as input.

- A frame rendered before saving equals the same frame rendered from the saved file in a new process.
- Two processes rendering frames 1-3 and 4-6 (`-s 1 -e 3 -a`, `-s 4 -e 6 -a`) write the same
  files as one process rendering 1-6.
"""

import os
import shutil
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from PIL import Image

# Every process starts like `blender -b`: user preferences read, extensions enabled.
_PRELUDE = """
import bpy, sys
bpy.ops.wm.read_userpref()
assert hasattr(bpy.types.Object, "nerf_deform"), "NeRF Deform is not enabled"
"""


def _blender(script: str, user_resources, cwd) -> str:
    env = {**os.environ, "BLENDER_USER_RESOURCES": str(user_resources)}
    env.pop("NUMBA_CACHE_DIR", None)  # a farm node's environment: the worker picks its own kernel cache
    proc = subprocess.run(
        [sys.executable, "-c", _PRELUDE + textwrap.dedent(script)],
        env=env,
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    return proc.stdout


@pytest.fixture(scope="module")
def farm(tmp_path_factory, extension_zip, sphere_nerf):
    """User preferences with the extension installed and the worker Python set, and a saved .blend
    whose camera orbits the NeRF over frames 1-6 (its checkpoint stored relative to it)."""
    root = tmp_path_factory.mktemp("farm")
    user = root / "user"
    install = f"""
    assert bpy.ops.extensions.package_install_files(filepath={str(extension_zip)!r}, repo="user_default",
                                                    enable_on_install=True) == {{"FINISHED"}}
    prefs = bpy.context.preferences.addons["bl_ext.user_default.blender_nerf_deform"].preferences
    prefs.worker_python = {sys.executable!r}
    bpy.ops.wm.save_userpref()
    """
    env = {**os.environ, "BLENDER_USER_RESOURCES": str(user)}
    proc = subprocess.run(
        [sys.executable, "-c", "import bpy\n" + textwrap.dedent(install)],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]

    ckpt, _ = sphere_nerf
    project = root / "project"
    shutil.copytree(ckpt.parent, project / "run")
    author = f"""
    import math
    for obj in list(bpy.data.objects):  # the default scene's cube, light and camera
        bpy.data.objects.remove(obj)
    bpy.ops.wm.save_as_mainfile(filepath={str(project / "shot.blend")!r})  # a path first: the checkpoint goes relative
    assert bpy.ops.nerf_deform.load_nerf(filepath={str(project / "run" / "nerf.ckpt")!r}) == {{"FINISHED"}}
    scene = bpy.context.scene
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(cam)
    scene.camera = cam
    cam.data.sensor_fit, cam.data.angle_x = "HORIZONTAL", 0.9
    for frame in range(1, 7):
        a = 0.6 * frame
        eye = (3 * math.cos(a), 3 * math.sin(a), 0.8)
        cam.location = eye
        cam.rotation_euler = (-cam.location).to_track_quat("-Z", "Y").to_euler()  # look at the NeRF
        cam.keyframe_insert("location", frame=frame)
        cam.keyframe_insert("rotation_euler", frame=frame)
    scene.frame_start, scene.frame_end = 1, 6
    scene.render.resolution_x = scene.render.resolution_y = 24
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGBA"
    scene.frame_set(3)
    scene.render.filepath = {str(project / "before_save_0003.png")!r}
    assert bpy.ops.render.render(write_still=True) == {{"FINISHED"}}
    bpy.ops.wm.save_as_mainfile(filepath={str(project / "shot.blend")!r})
    (nerf,) = [o for o in bpy.data.objects if o.nerf_deform.role == "NERF"]
    print("CHECKPOINT", nerf.nerf_deform.checkpoint)
    """
    out = _blender(author, user, project)
    assert "CHECKPOINT //run" in out.replace("\\\\", "/"), out[-1000:]
    return user, project


def _render_range(farm, start, end, folder):
    user, project = farm
    script = f"""
    bpy.ops.wm.open_mainfile(filepath={str(project / "shot.blend")!r})
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = {start}, {end}
    scene.render.filepath = {str(project / folder) + "/frame_"!r}
    assert bpy.ops.render.render(animation=True) == {{"FINISHED"}}
    """
    _blender(script, user, project)


def _pixels(path):
    return np.asarray(Image.open(path).convert("RGBA"))


@pytest.mark.slow
def test_split_frame_ranges_write_the_same_files_as_one_process(farm):
    _, project = farm
    _render_range(farm, 1, 6, "whole")
    _render_range(farm, 1, 3, "split")
    _render_range(farm, 4, 6, "split")
    whole = sorted(p.name for p in (project / "whole").iterdir())
    assert whole == [f"frame_000{k}.png" for k in range(1, 7)]
    assert sorted(p.name for p in (project / "split").iterdir()) == whole
    frames = [_pixels(project / "whole" / name) for name in whole]
    # Every frame compared before failing, with how far apart they are (a farm needs identical files).
    differing = []
    for name, frame in zip(whole, frames):
        diff = np.abs(frame.astype(int) - _pixels(project / "split" / name).astype(int))
        if diff.any():
            differing.append(
                f"{name}: {int((diff.max(-1) > 0).sum())} of {diff.shape[0] * diff.shape[1]} pixels "
                f"differ, by up to {int(diff.max())}/255"
            )
    assert not differing, "; ".join(differing)
    # The workers wrote their compiled files (numba kernels, bytecode of the engine's torch
    # modules, which Blender itself never imports) under the user folder, not into the extension.
    user, _ = farm
    (extension,) = user.glob("extensions/*/blender_nerf_deform")
    assert not [
        p
        for p in extension.rglob("*")
        if p.suffix in (".nbi", ".nbc") or p.name.startswith("renderer.") and p.suffix == ".pyc"
    ]
    assert list(user.glob("extensions/.user/*/blender_nerf_deform/worker/numba_cache/**/*.nbi"))
    # The camera moves: the frames are not all the same picture.
    assert not np.array_equal(frames[0], frames[5])
    assert frames[0][..., 3].max() > 100


@pytest.mark.slow
def test_frame_rendered_before_saving_equals_it_rendered_from_the_saved_file(farm):
    _, project = farm
    if not (project / "whole").exists():
        _render_range(farm, 1, 6, "whole")
    assert np.array_equal(_pixels(project / "before_save_0003.png"), _pixels(project / "whole" / "frame_0003.png"))
