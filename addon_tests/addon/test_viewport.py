"""The viewport's progressive render (Rendered shading), headless: the request and refinement logic
with the real worker. The bpy module has no GPU context, so the draw itself (a GPUTexture through
Blender's display shader) is not exercised here; what it draws is `ViewportRender.image`.

- The camera view's pinhole is F12's (the region's matrices are the scene camera's there).
- Coarse first (1/8), then 1/4, 1/2 and full; the full image is F12's frame, for one NeRF or two.
- A new view or a new pose restarts from coarse; a render that was refining is cancelled in the
  worker and its answer never shown; changes while a coarse image renders let it land, then the
  newest state renders (those in between skipped); a change that moves nothing restarts nothing.
- An orthographic view draws nothing and says why once.
"""

import json
import time

import numpy as np
import pytest
from fixtures.blender_objects import scene_with_nerf

SIZE = 32


def _camera_view(bpy, camera, width, height):
    """The pinhole of a 3D View looking through `camera`, from the matrices Blender gives that view."""
    from blender_nerf_deform.addon.render.viewport import pinhole_from_view

    scene = bpy.context.scene
    depsgraph = bpy.context.evaluated_depsgraph_get()
    window = camera.calc_matrix_camera(
        depsgraph, x=width, y=height, scale_x=scene.render.pixel_aspect_x, scale_y=scene.render.pixel_aspect_y
    )
    return pinhole_from_view(camera.matrix_world.inverted(), window, width, height)


def _pump(viewport, client, seconds=120):
    """What Blender's timer does on the main thread, until the render under way stops."""
    deadline = time.monotonic() + seconds
    while viewport.render is not None and viewport.render.state == "running" and time.monotonic() < deadline:
        client.drain()
        time.sleep(0.01)
    return viewport.render.state if viewport.render is not None else None


class _Redraws:
    """Records what the view would draw at each redraw: (render, downscale of the image)."""

    def __init__(self):
        self.viewport = None
        self.shown = []

    def __call__(self):
        self.shown.append((self.viewport.render, self.viewport.shown_downscale))


def _viewport(bpy):
    from blender_nerf_deform.addon.render.viewport import ViewportRender
    from blender_nerf_deform.addon.worker import jobs

    redraws = _Redraws()
    viewport = redraws.viewport = ViewportRender(redraws)
    return viewport, redraws, jobs.worker(bpy.context)


def test_the_camera_view_is_framed_as_f12(addon):
    bpy = addon
    from blender_nerf_deform.addon.data.camera import pinhole_from_blender

    scene = bpy.context.scene
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(camera)
    scene.camera = camera
    camera.location, camera.rotation_euler = (1.0, -4.0, 2.0), (1.1, 0.1, 0.3)
    for fit, shift, (width, height) in (
        ("AUTO", (0.0, 0.0), (64, 40)),
        ("VERTICAL", (0.1, -0.05), (30, 50)),
        ("HORIZONTAL", (-0.2, 0.15), (48, 48)),
    ):
        camera.data.sensor_fit, (camera.data.shift_x, camera.data.shift_y) = fit, shift
        camera.data.lens = 35.0
        scene.render.resolution_x, scene.render.resolution_y = width, height
        scene.render.resolution_percentage = 100
        bpy.context.view_layer.update()
        f12 = pinhole_from_blender(scene, camera)
        view = _camera_view(bpy, camera, width, height)
        for name in ("width", "height", "fx", "fy", "cx", "cy"):
            assert getattr(view, name) == pytest.approx(getattr(f12, name), rel=1e-5), (fit, name)
        assert np.allclose(view.camera_to_world, f12.camera_to_world, atol=1e-5)


def test_an_orthographic_view_draws_nothing_and_says_why_once(addon, capsys):
    from mathutils import Matrix

    from blender_nerf_deform.addon.data.camera import CameraError
    from blender_nerf_deform.addon.render.viewport import ViewportRender, pinhole_from_view

    ortho = Matrix.Identity(4)
    ortho[0][0] = ortho[1][1] = 0.2
    ortho[2][2], ortho[2][3] = -0.02, -1.0
    with pytest.raises(CameraError, match="perspective views only"):
        pinhole_from_view(Matrix.Identity(4), ortho, 40, 30)
    viewport = ViewportRender()
    for _ in range(3):  # every redraw of that view
        try:
            pinhole_from_view(Matrix.Identity(4), ortho, 40, 30)
        except CameraError as error:
            viewport.refuse_view(str(error))
    assert viewport.image is None and viewport.render is None
    assert viewport.status.startswith("NeRF Deform: NeRF Deform draws perspective views only")
    assert capsys.readouterr().out.count("perspective views only") == 1


@pytest.mark.slow
@pytest.mark.parametrize("count", [1, 2], ids=["one_nerf", "two_nerfs"])
def test_coarse_first_then_finer_and_the_last_image_is_f12s(addon, sphere_nerf, count):
    bpy = addon
    from mathutils import Matrix

    from blender_nerf_deform.addon.render.frame import render_frame

    ckpt, data = sphere_nerf
    meta = json.loads((data / "transforms.json").read_text())
    _nerf, camera = scene_with_nerf(bpy, ckpt, meta["frames"][2], meta["camera_angle_x"], SIZE)
    if count == 2:  # a second NeRF, nearer the camera, covering part of the first
        assert bpy.ops.nerf_deform.load_nerf(filepath=str(ckpt)) == {"FINISHED"}
        bpy.context.active_object.matrix_world = camera.matrix_world @ Matrix.Translation((0.6, 0.2, -1.8))
    viewport, redraws, client = _viewport(bpy)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    viewport.update_scene(depsgraph)
    viewport.update_view(_camera_view(bpy, camera, SIZE, SIZE))
    assert _pump(viewport, client) == "finished", viewport.render.error
    assert [downscale for _render, downscale in redraws.shown] == [8, 4, 2, 1]
    assert viewport.render.delivered == [(4, 4), (8, 8), (16, 16), (32, 32)]
    assert viewport.status == ""

    f12 = render_frame(depsgraph, SIZE, SIZE)
    assert not f12.error
    # The camera view's matrices are float32 (Blender's), F12's intrinsics float64: rays differ by
    # ~1e-7, which moves the fixed-step samples a little: the same picture up to that. Where a sample
    # sits on an occupancy cell's face, that shift can skip or keep it, a step of one sample's opacity
    # (1.6e-3 at a silhouette pixel for the NeRF trained with one thread): a handful of pixels at most.
    covered = f12.rgba[..., 3] > 0.5
    differs = np.abs(viewport.image - f12.rgba).max(axis=-1) > 1e-4
    assert differs.sum() <= 0.01 * differs.size, f"{differs.sum()} of {differs.size} pixels differ from F12's"
    assert np.abs(viewport.image - f12.rgba).max() < 1e-2
    same = covered & ~differs
    assert same.sum() > 0.9 * covered.sum()
    assert np.allclose(viewport.depth[same], f12.depth[same], rtol=1e-5)


@pytest.mark.slow
def test_a_new_view_or_pose_restarts_from_coarse_and_nothing_else_does(addon, sphere_nerf):
    bpy = addon
    from mathutils import Matrix

    from blender_nerf_deform.addon.data.cage_store import store_cage
    from blender_nerf_deform.engine.geometry.cage import box_cage

    ckpt, data = sphere_nerf
    meta = json.loads((data / "transforms.json").read_text())
    nerf, camera = scene_with_nerf(bpy, ckpt, meta["frames"][4], meta["camera_angle_x"], SIZE)
    rest, tets = box_cage((3, 3, 3), lo=(-1.5, -1.5, -1.5), hi=(1.5, 1.5, 1.5))
    cage = bpy.data.objects.new("Cage", bpy.data.meshes.new("Cage"))
    store_cage(cage.data, rest, tets)
    cage.nerf_deform.role = "CAGE"
    bpy.context.scene.collection.objects.link(cage)
    cage.parent = nerf
    nerf.nerf_deform.cage, nerf.nerf_deform.deformation_mode = cage, "MODIFIERS"

    viewport, redraws, client = _viewport(bpy)
    view = _camera_view(bpy, camera, SIZE, SIZE)
    viewport.update_scene(bpy.context.evaluated_depsgraph_get())
    viewport.update_view(view)
    assert _pump(viewport, client) == "finished"
    assert viewport.restarts == 1

    # Redraws of the same view, and depsgraph updates that move no NeRF, render nothing again.
    viewport.update_view(view)
    bpy.context.scene.collection.objects.link(bpy.data.objects.new("Unrelated", None))
    viewport.update_scene(bpy.context.evaluated_depsgraph_get())
    assert viewport.restarts == 1

    # The view orbits: from coarse again, to full.
    camera.matrix_world = Matrix.Rotation(0.3, 4, "Z") @ camera.matrix_world
    redraws.shown.clear()
    viewport.update_view(_camera_view(bpy, camera, SIZE, SIZE))
    assert viewport.restarts == 2
    assert _pump(viewport, client) == "finished"
    assert [downscale for _render, downscale in redraws.shown] == [8, 4, 2, 1]
    orbited = viewport.image

    # The pose changes (the cage's modifiers' result: here its placement): from coarse again.
    cage.location = (0.3, -0.2, 0.25)
    redraws.shown.clear()
    viewport.update_scene(bpy.context.evaluated_depsgraph_get())
    assert viewport.restarts == 3
    assert _pump(viewport, client) == "finished"
    assert [downscale for _render, downscale in redraws.shown] == [8, 4, 2, 1]
    assert not np.array_equal(viewport.image, orbited)


def _spy_cancels(client):
    """Record the request ids the client cancels (each still goes to the worker)."""
    cancels, real_cancel = [], client.cancel
    client.cancel = lambda request_id: (cancels.append(request_id), real_cancel(request_id))
    return cancels, lambda: setattr(client, "cancel", real_cancel)


@pytest.mark.slow
def test_a_change_while_refining_cancels_the_stale_request_and_it_is_never_shown(addon, sphere_nerf):
    bpy = addon
    from mathutils import Matrix

    ckpt, data = sphere_nerf
    meta = json.loads((data / "transforms.json").read_text())
    _nerf, camera = scene_with_nerf(bpy, ckpt, meta["frames"][1], meta["camera_angle_x"], SIZE)
    viewport, redraws, client = _viewport(bpy)
    cancels, restore = _spy_cancels(client)
    try:
        viewport.update_scene(bpy.context.evaluated_depsgraph_get())
        viewport.update_view(_camera_view(bpy, camera, 8 * SIZE, 8 * SIZE))  # 256 px: refining takes a while
        stale = viewport.render
        deadline = time.monotonic() + 120
        while not stale.delivered and time.monotonic() < deadline:  # until the coarse image is shown
            client.drain()
            time.sleep(0.005)
        assert stale.state == "running" and stale.step >= 1  # a finer step is in the worker
        refining = stale.sent[-1]
        camera.matrix_world = Matrix.Rotation(-0.4, 4, "Z") @ camera.matrix_world
        redraws.shown.clear()
        viewport.update_view(_camera_view(bpy, camera, SIZE, SIZE))
        assert stale.state == "cancelled" and cancels == [refining]
        assert _pump(viewport, client) == "finished"
    finally:
        restore()
    # Whatever the worker answered the stale request (its image or "cancelled"), only the new
    # render's images were shown after the change, coarse first.
    assert all(render is viewport.render for render, _ in redraws.shown)
    assert [downscale for _render, downscale in redraws.shown] == [8, 4, 2, 1]
    assert len(stale.delivered) == stale.step  # its refining answer, if it came, was dropped


@pytest.mark.slow
def test_changes_while_the_coarse_image_renders_let_it_land_then_the_newest_renders(addon, sphere_nerf):
    bpy = addon
    from mathutils import Matrix

    ckpt, data = sphere_nerf
    meta = json.loads((data / "transforms.json").read_text())
    _nerf, camera = scene_with_nerf(bpy, ckpt, meta["frames"][1], meta["camera_angle_x"], SIZE)
    viewport, redraws, client = _viewport(bpy)
    cancels, restore = _spy_cancels(client)
    try:
        viewport.update_scene(bpy.context.evaluated_depsgraph_get())
        viewport.update_view(_camera_view(bpy, camera, SIZE, SIZE))
        first = viewport.render
        for angle in (0.2, 0.2):  # a drag: two more views before the first coarse image came back
            camera.matrix_world = Matrix.Rotation(angle, 4, "Z") @ camera.matrix_world
            viewport.update_view(_camera_view(bpy, camera, SIZE, SIZE))
        assert viewport.render is first and cancels == []
        deadline = time.monotonic() + 120
        while (viewport.render is first or viewport.render.state == "running") and time.monotonic() < deadline:
            client.drain()
            time.sleep(0.01)
    finally:
        restore()
    newest = viewport.render
    assert first.state == "superseded" and first.delivered == [(4, 4)]
    assert newest.state == "finished" and viewport.restarts == 2  # the view in between was never rendered
    assert redraws.shown == [(first, 8), (newest, 8), (newest, 4), (newest, 2), (newest, 1)]
    assert newest.pinhole == _camera_view(bpy, camera, SIZE, SIZE)


@pytest.mark.slow
def test_a_failing_nerf_shows_its_error_in_the_view(addon, sphere_nerf, tmp_path):
    bpy = addon
    import shutil

    ckpt, data = sphere_nerf
    meta = json.loads((data / "transforms.json").read_text())
    moved = tmp_path / "nerf.ckpt"
    shutil.copy(ckpt, moved)
    nerf, camera = scene_with_nerf(bpy, moved, meta["frames"][1], meta["camera_angle_x"], SIZE)
    moved.unlink()  # the checkpoint is gone: the worker refuses the request
    viewport, _redraws, client = _viewport(bpy)
    viewport.update_scene(bpy.context.evaluated_depsgraph_get())
    viewport.update_view(_camera_view(bpy, camera, SIZE, SIZE))
    assert _pump(viewport, client) == "failed"
    assert viewport.image is None
    assert "does not exist" in viewport.status and viewport.status.startswith("NeRF Deform: ")


def _gpu_available(bpy) -> bool:
    """Whether this Blender has a GPU context, bringing it up where it can. The bpy module in background
    mode starts its GPU backend only when a render needs one: a 4x4 Workbench render of a scratch scene
    does (headless, through EGL: on a machine without a GPU, Mesa's llvmpipe), after which the gpu
    module draws offscreen as in Blender's window."""
    import gpu

    def offscreen_works() -> bool:
        try:
            gpu.types.GPUOffScreen(4, 4).free()
        except SystemError:  # "GPU functions for drawing are not available in background mode"
            return False
        return True

    if offscreen_works():
        return True
    scratch = bpy.data.scenes.new("GPU context")
    camera = bpy.data.objects.new("GPU context", bpy.data.cameras.new("GPU context"))
    try:
        scratch.collection.objects.link(camera)
        scratch.camera = camera
        scratch.render.engine = "BLENDER_WORKBENCH"
        scratch.render.resolution_x = scratch.render.resolution_y = 4
        bpy.ops.render.render(scene=scratch.name)
    finally:
        data = camera.data
        bpy.data.objects.remove(camera)
        bpy.data.cameras.remove(data)
        bpy.data.scenes.remove(scratch)
    return offscreen_works()


def test_the_viewport_texture_draws_the_image_upright(addon):
    """view_draw's texture, drawn as view_draw draws it, reads back as the image (top row on top).
    Needs a GPU context: in the bpy module headless, the one a Workbench render brings up (EGL)."""
    bpy = addon
    if not _gpu_available(bpy):  # no EGL at all (no libEGL, or no device it can open): say so
        pytest.skip("no GPU context: this Blender could not bring up its GPU backend headless (EGL)")
    import gpu
    from gpu_extras.presets import draw_texture_2d
    from mathutils import Matrix

    from blender_nerf_deform.addon.render.render_engine import image_texture

    h, w = 12, 20
    image = np.zeros((h, w, 4), np.float32)
    image[..., 0] = np.linspace(0, 1, w)[None, :]
    image[..., 1] = np.linspace(1, 0, h)[:, None]  # green at the top row
    image[..., 3] = 1.0
    offscreen = gpu.types.GPUOffScreen(w, h, format="RGBA16F")
    try:
        with offscreen.bind():
            fb = gpu.state.active_framebuffer_get()
            fb.clear(color=(0.0, 0.0, 0.0, 0.0))
            with gpu.matrix.push_pop():
                gpu.matrix.load_matrix(Matrix.Identity(4))
                gpu.matrix.load_projection_matrix(Matrix.Identity(4))
                gpu.matrix.translate((-1.0, -1.0))
                gpu.matrix.scale((2.0 / w, 2.0 / h))
                draw_texture_2d(image_texture(image), (0, 0), w, h)
            read = np.array(fb.read_color(0, 0, w, h, 4, 0, "FLOAT").to_list(), np.float32).reshape(h, w, 4)
    finally:
        offscreen.free()
    assert np.allclose(read[::-1], image, atol=2e-3)  # framebuffer rows run bottom-up
