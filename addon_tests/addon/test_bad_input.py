"""Bad input through the add-on: each case gives a report naming the problem, leaves the scene as it
was, and the next operation works.

Covered elsewhere (not repeated here): a handle from an empty selection (test_handles), Build Cage
on a NeRF without a mesh (test_build_cage: the report and the untouched scene; here: that Extract
Mesh and Build Cage then work), a worker Python without torch or missing (test_worker), a worker
job cancelled midway at the protocol level (test_worker).

A camera inside the cage is not bad input: ray bending starts every ray at the camera, wherever it
is, so the tests here check that such a camera renders correctly rather than that it is refused.
"""

import re
import shutil
import threading
import time

import numpy as np
import pytest
from fixtures import psnr as _psnr
from PIL import Image


def _camera(bpy, location, target=(0.0, 0.0, 0.0), size=32, angle_x=1.2):
    from mathutils import Vector

    scene = bpy.context.scene
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.data.sensor_fit, camera.data.angle_x = "HORIZONTAL", angle_x
    scene.collection.objects.link(camera)
    scene.camera = camera
    camera.location = location
    camera.rotation_euler = (Vector(target) - Vector(location)).to_track_quat("-Z", "Y").to_euler()
    scene.render.resolution_x = scene.render.resolution_y = size
    scene.render.resolution_percentage = 100
    settings = scene.render.image_settings
    settings.file_format, settings.color_mode, settings.color_depth = "PNG", "RGBA", "8"
    return camera


def _render(bpy, path):
    bpy.context.scene.render.filepath = str(path)
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    return np.asarray(Image.open(path).convert("RGBA"), dtype=np.float64) / 255


def _scene_state(bpy):
    """What a failed operation must not change: objects, their roles, links and NeRF paths."""
    return sorted(
        (
            o.name,
            o.type,
            o.nerf_deform.role,
            o.parent.name if o.parent else "",
            o.nerf_deform.checkpoint,
            o.nerf_deform.surface.name if o.nerf_deform.surface else "",
            o.nerf_deform.cage.name if o.nerf_deform.cage else "",
            len(o.data.vertices) if o.type == "MESH" else -1,
        )
        for o in bpy.data.objects
    )


def test_load_nerf_on_a_missing_file_names_it_and_the_next_load_works(addon, sphere_nerf, tmp_path):
    bpy = addon
    ckpt, _ = sphere_nerf
    scene = bpy.context.scene
    engine = scene.render.engine
    missing = tmp_path / "runs" / "nerf.ckpt"
    with pytest.raises(RuntimeError, match=re.escape(f"Load NeRF: checkpoint {missing} does not exist")):
        bpy.ops.nerf_deform.load_nerf(filepath=str(missing))
    assert len(bpy.data.objects) == 0 and scene.render.engine == engine  # the scene was not prepared either

    assert bpy.ops.nerf_deform.load_nerf(filepath=str(ckpt)) == {"FINISHED"}
    (nerf,) = bpy.data.objects
    assert nerf.nerf_deform.role == "NERF" and scene.render.engine == "NERF_DEFORM"


@pytest.mark.slow
def test_moved_checkpoint_is_named_by_render_and_extract_and_both_work_once_it_is_found(addon, sphere_nerf, tmp_path):
    bpy = addon
    ckpt, _ = sphere_nerf
    run = tmp_path / "run"
    shutil.copytree(ckpt.parent, run)
    assert bpy.ops.nerf_deform.load_nerf(filepath=str(run / "nerf.ckpt")) == {"FINISHED"}
    nerf = bpy.context.active_object
    nerf.nerf_deform.resolution = 32
    _camera(bpy, (0.0, -3.0, 0.8))

    # Build Cage before Extract Mesh: said, nothing made.
    before = _scene_state(bpy)
    with pytest.raises(RuntimeError, match="has no extracted mesh yet: run Extract Mesh first"):
        bpy.ops.nerf_deform.build_cage()
    assert _scene_state(bpy) == before

    # The checkpoint moves away (another folder, a renamed run): render and extract name the path they looked at.
    shutil.move(run, tmp_path / "elsewhere")
    expected = f"NeRF checkpoint {run / 'nerf.ckpt'} does not exist"
    with pytest.raises(RuntimeError, match=re.escape(f"NeRF Deform: {expected}")):
        bpy.ops.render.render()
    bpy.context.view_layer.objects.active = nerf
    with pytest.raises(RuntimeError, match=re.escape(f"Extract Mesh: {expected}")):
        bpy.ops.nerf_deform.extract_mesh()
    assert _scene_state(bpy) == before  # no half-made mesh, the stored path as it was

    # The artist points the NeRF at where the checkpoint is now: everything works again.
    nerf.nerf_deform.checkpoint = str(tmp_path / "elsewhere" / "nerf.ckpt")
    image = _render(bpy, tmp_path / "found.png")
    assert image[..., 3].max() > 0.5
    assert bpy.ops.nerf_deform.extract_mesh() == {"FINISHED"}
    assert nerf.nerf_deform.surface is not None and len(nerf.nerf_deform.surface.data.polygons) > 100
    bpy.context.view_layer.objects.active = nerf
    assert bpy.ops.nerf_deform.build_cage() == {"FINISHED"}
    assert nerf.nerf_deform.cage is not None


def _nerf_in_a_box_cage(bpy, ckpt):
    """A NeRF whose cage (Cage Modifiers mode) is a box around its whole scene box."""
    from blender_nerf_deform.addon.data.cage_store import store_cage
    from blender_nerf_deform.engine.geometry.cage import box_cage

    assert bpy.ops.nerf_deform.load_nerf(filepath=str(ckpt)) == {"FINISHED"}
    nerf = bpy.context.active_object
    rest, tets = box_cage((4, 4, 4), lo=(-1.5, -1.5, -1.5), hi=(1.5, 1.5, 1.5))
    cage = bpy.data.objects.new("Cage", bpy.data.meshes.new("Cage"))
    store_cage(cage.data, rest, tets)
    cage.nerf_deform.role = "CAGE"
    bpy.context.scene.collection.objects.link(cage)
    cage.parent = nerf
    return nerf, cage


@pytest.mark.slow
def test_camera_inside_the_cage_renders_the_bent_nerf_correctly(addon, sphere_nerf, tmp_path):
    """Decided behaviour: rendering from inside the cage is supported (a camera can fly through a
    deformed NeRF); rays start at the camera inside a tet and are bent like any other."""
    bpy = addon
    from mathutils import Matrix, Vector

    ckpt, _ = sphere_nerf
    nerf, cage = _nerf_in_a_box_cage(bpy, ckpt)
    # Inside the cage and the NeRF's box, outside the sphere (radius 0.8), looking at it closely.
    camera = _camera(bpy, (0.0, -1.2, 0.3))
    plain = _render(bpy, tmp_path / "plain.png")
    assert plain[..., 3].max() > 0.9 and plain[..., 3].min() < 0.1  # the sphere and empty space in view

    nerf.nerf_deform.cage, nerf.nerf_deform.deformation_mode = cage, "MODIFIERS"
    rest_pose = _render(bpy, tmp_path / "rest_pose.png")
    # Bent through the undeformed cage: the plain NeRF, to float rounding (identity-bent frames differ
    # from plain ones by ~1e-5, 96.9 dB on the lego: BENCHMARKS), so a pixel on an 8-bit rounding
    # boundary may flip by one level; the bar for the identity is 50 dB.
    assert _psnr(rest_pose, plain) >= 50

    shift = Vector((0.3, -0.2, 0.25))
    cage.location = shift  # the camera stays inside the moved cage: y from -1.7 to 1.3
    moved_content = _render(bpy, tmp_path / "moved_content.png")
    cage.location = (0.0, 0.0, 0.0)
    camera.matrix_world = Matrix.Translation(-shift) @ camera.matrix_world
    moved_camera = _render(bpy, tmp_path / "moved_camera.png")
    assert _psnr(moved_content, moved_camera) >= 35
    assert _psnr(moved_content, plain) < _psnr(moved_content, moved_camera) - 10


@pytest.mark.slow
def test_render_whose_worker_job_is_cancelled_midway_reports_it_and_the_next_render_works(addon, sphere_nerf, tmp_path):
    """The RenderEngine waits on its worker job with Blender's test_break; Esc cannot be pressed
    headless, so the job is cancelled through the worker client, as test_break's cancel does. A
    cancel Blender did not ask for must not pass an empty frame off as a render."""
    bpy = addon
    from blender_nerf_deform.addon.worker import jobs

    ckpt, _ = sphere_nerf
    assert bpy.ops.nerf_deform.load_nerf(filepath=str(ckpt)) == {"FINISHED"}
    _camera(bpy, (0.0, -3.0, 0.8), size=320)  # many ray chunks: the job is still running when the cancel comes
    client = jobs.worker(bpy.context)
    client.call("info")  # started before the render, so the only blocking request below is the render's
    cancelled = []

    def cancel_the_render():
        deadline = time.monotonic() + 120
        while not cancelled and time.monotonic() < deadline:
            with client._lock:
                waiting = [r.id for r in client._requests.values() if r.blocking]
            if waiting:
                client.cancel(waiting[0])
                cancelled.append(waiting[0])
            time.sleep(0.001)

    canceller = threading.Thread(target=cancel_the_render)
    canceller.start()
    before = _scene_state(bpy)
    try:
        with pytest.raises(RuntimeError, match="the render of frame 1 was cancelled in the NeRF worker"):
            bpy.ops.render.render()
    finally:
        canceller.join()
    assert cancelled and _scene_state(bpy) == before

    bpy.context.scene.render.resolution_x = bpy.context.scene.render.resolution_y = 32
    image = _render(bpy, tmp_path / "next.png")
    assert image.shape == (32, 32, 4) and image[..., 3].max() > 0.5
