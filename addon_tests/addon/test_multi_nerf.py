"""Several NeRF objects in one scene: each rendered by the worker, merged per pixel front to back by depth.

The same small sphere NeRF (sphere_nerf, radius 0.8) is loaded twice and placed apart or one behind
the other; every expectation comes from renders of each NeRF alone (the other hidden), so what is
checked is the merge itself: side by side, each half is the lone NeRF's render; one behind the
other, the front one occludes, per pixel, and gives the Depth pass.
"""

import subprocess
import sys
import textwrap

import numpy as np
import pytest
from fixtures import REPO
from fixtures.blender_objects import render_exr_passes
from fixtures.sphere_data import look_at

WIDTH, HEIGHT = 64, 40


def _two_nerfs(bpy, ckpt, first_at, second_at, eye, target=(0.0, 0.0, 0.0)):
    """Two NeRF objects of `ckpt` placed at `first_at` and `second_at`, a camera at `eye` looking at `target`."""
    from mathutils import Matrix

    nerfs = []
    for name, location in (("Near", first_at), ("Far", second_at)):
        assert bpy.ops.nerf_deform.load_nerf(filepath=str(ckpt)) == {"FINISHED"}
        nerf = bpy.context.active_object
        nerf.name = name
        nerf.location = location
        nerfs.append(nerf)
    scene = bpy.context.scene
    cam_data = bpy.data.cameras.new("Camera")
    cam_data.sensor_fit, cam_data.angle_x = "HORIZONTAL", 0.9
    camera = bpy.data.objects.new("Camera", cam_data)
    scene.collection.objects.link(camera)
    scene.camera = camera
    camera.matrix_world = Matrix(look_at(eye, target).tolist())
    scene.render.resolution_x, scene.render.resolution_y = WIDTH, HEIGHT
    scene.render.resolution_percentage = 100
    return nerfs


def _render_alone(bpy, nerfs, keep, path):
    for nerf in nerfs:
        nerf.hide_render = nerf is not keep
    passes = render_exr_passes(bpy, path)
    for nerf in nerfs:
        nerf.hide_render = False
    return passes


@pytest.mark.slow
def test_two_nerfs_side_by_side_render_both_as_each_alone(addon, sphere_nerf, tmp_path):
    bpy = addon
    ckpt, _ = sphere_nerf
    # 3.6 apart: the NeRFs' boxes ([-1.5, 1.5]^3 each, holding whatever faint floaters the short
    # training left) do not meet, so each lies wholly in its half of the picture.
    left, right = _two_nerfs(bpy, ckpt, (-1.8, 0.0, 0.0), (1.8, 0.0, 0.0), eye=(0.0, -7.0, 0.0))
    alone_left = _render_alone(bpy, [left, right], left, tmp_path / "left.exr")
    alone_right = _render_alone(bpy, [left, right], right, tmp_path / "right.exr")
    both = render_exr_passes(bpy, tmp_path / "both.exr")

    half = WIDTH // 2
    # Each sphere is in its half of the picture, and nothing of it in the other half.
    assert alone_left["Alpha"][:, :half].max() > 0.9 and alone_left["Alpha"][:, half:].max() == 0
    assert alone_right["Alpha"][:, half:].max() > 0.9 and alone_right["Alpha"][:, :half].max() == 0
    for alone, columns in ((alone_left, slice(0, half)), (alone_right, slice(half, WIDTH))):
        assert np.allclose(both["Combined"][:, columns], alone["Combined"][:, columns], rtol=1e-5, atol=1e-5)
        assert np.allclose(both["Depth"][:, columns], alone["Depth"][:, columns], rtol=1e-5, atol=1e-5)
        assert (alone["Alpha"][:, columns] > 0.5).sum() > 30
    assert np.all(both["Depth"][both["Alpha"] <= 1e-6] == 1e10)

    # A NeRF in a collection excluded from the view layer is not rendered, as a hidden one.
    collection = bpy.data.collections.new("Right side")
    bpy.context.scene.collection.children.link(collection)
    for users in list(right.users_collection):
        users.objects.unlink(right)
    collection.objects.link(right)
    bpy.context.view_layer.layer_collection.children[collection.name].exclude = True
    excluded = render_exr_passes(bpy, tmp_path / "excluded.exr")
    assert np.allclose(excluded["Combined"], alone_left["Combined"], rtol=1e-5, atol=1e-5)


@pytest.mark.slow
def test_the_nerf_in_front_occludes_the_one_behind_pixel_by_pixel(addon, sphere_nerf, tmp_path):
    bpy = addon
    ckpt, _ = sphere_nerf
    # "Far" 2.5 units behind "Near" and shifted sideways: partly hidden by it, partly seen beside it.
    near, far = _two_nerfs(bpy, ckpt, (0.0, 0.0, 0.0), (0.9, 2.5, 0.0), eye=(0.0, -4.0, 0.0), target=(0.3, 0.0, 0.0))
    front = _render_alone(bpy, [near, far], near, tmp_path / "near.exr")
    back = _render_alone(bpy, [near, far], far, tmp_path / "far.exr")
    both = render_exr_passes(bpy, tmp_path / "both.exr")

    a_front, a_back = front["Alpha"], back["Alpha"]
    overlap = (a_front > 0.5) & (a_back > 0.5)
    only_back = (a_back > 0.5) & (a_front < 1e-3)
    assert overlap.sum() > 30 and only_back.sum() > 30  # the far NeRF is both hidden and seen
    # Where both cover the pixel, the near one is nearer, by about the 2.5 units between them.
    assert np.all(front["Depth"][overlap] < back["Depth"][overlap] - 1.5)
    # "over", front to back: the near NeRF's colour, then the far one's through what it lets pass.
    expected = front["Combined"] + (1.0 - a_front[..., None]) * back["Combined"]
    assert np.allclose(both["Combined"][overlap], expected[overlap], atol=1e-5)
    assert np.allclose(both["Combined"][only_back], back["Combined"][only_back], atol=1e-3)
    solid_front = overlap & (a_front > 0.99)
    assert solid_front.sum() > 10
    assert np.allclose(both["Combined"][solid_front], front["Combined"][solid_front], atol=1e-2)
    # The Depth pass is the front NeRF's wherever it covers the pixel, the far one's where only it does.
    # (To float32 rounding: two renders of one NeRF may differ by ~1e-6 relative; a clean-clone run hit it.)
    assert np.allclose(both["Depth"][overlap], front["Depth"][overlap], rtol=1e-5, atol=1e-5)
    assert np.allclose(both["Depth"][only_back], back["Depth"][only_back], rtol=1e-5, atol=1e-5)

    # Swapped names (so the other one comes first in the list): the same picture, the order is by depth.
    near.name, far.name = "B near", "A far"
    swapped = render_exr_passes(bpy, tmp_path / "swapped.exr")
    assert np.allclose(swapped["Combined"], both["Combined"], atol=1e-6)


@pytest.mark.slow
def test_progress_spans_every_nerf_and_cancel_stops_between_them(addon, sphere_nerf):
    bpy = addon
    from blender_nerf_deform.addon.render import frame as frame_render
    from blender_nerf_deform.addon.worker import jobs

    ckpt, _ = sphere_nerf
    _two_nerfs(bpy, ckpt, (-1.8, 0.0, 0.0), (1.8, 0.0, 0.0), eye=(0.0, -7.0, 0.0))
    depsgraph = bpy.context.evaluated_depsgraph_get()
    fractions, statuses = [], []
    frame = frame_render.render_frame(
        depsgraph, WIDTH, HEIGHT, on_progress=lambda f, _m: fractions.append(f), on_status=statuses.append
    )
    assert not frame.error and not frame.cancelled
    # The first NeRF reports over [0, 0.5], the second over [0.5, 1].
    assert fractions == sorted(fractions) and min(fractions) <= 0.5 < max(fractions) == 1.0
    assert [s.split(",")[0] for s in statuses] == [
        "NeRF Deform: rendering Far (1 of 2)",
        "NeRF Deform: rendering Near (2 of 2)",
    ]

    # Esc once the first NeRF has rendered: the second is never sent.
    client = jobs.worker(bpy.context)
    renders_before = sum(op == "render" for op, _ in client.sent)
    first_done = []
    frame = frame_render.render_frame(
        depsgraph,
        WIDTH,
        HEIGHT,
        on_progress=lambda f, _m: first_done.append(f >= 0.5),
        should_cancel=lambda: any(first_done),
    )
    assert frame.cancelled and not frame.error
    assert sum(op == "render" for op, _ in client.sent) - renders_before == 1


@pytest.mark.slow
def test_a_saved_scene_of_two_nerfs_renders_the_same_in_a_fresh_blender(addon, sphere_nerf, tmp_path):
    bpy = addon
    ckpt, _ = sphere_nerf
    _two_nerfs(bpy, ckpt, (0.0, 0.0, 0.0), (0.9, 2.5, 0.0), eye=(0.0, -4.0, 0.0), target=(0.3, 0.0, 0.0))
    before = render_exr_passes(bpy, tmp_path / "before.exr")
    blend = tmp_path / "two.blend"
    assert bpy.ops.wm.save_as_mainfile(filepath=str(blend)) == {"FINISHED"}

    script = f"""
    import bpy, blender_nerf_deform
    blender_nerf_deform.register()
    bpy.ops.wm.open_mainfile(filepath={str(blend)!r})
    assert len([o for o in bpy.data.objects if o.nerf_deform.role == "NERF"]) == 2
    bpy.context.scene.render.filepath = {str(tmp_path / "after.exr")!r}
    assert bpy.ops.render.render(write_still=True) == {{"FINISHED"}}
    """
    proc = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(script)], cwd=REPO, capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    import OpenEXR

    with OpenEXR.File(str(tmp_path / "after.exr"), separate_channels=True) as exr:
        channels = {
            name.split(".")[-2] + "." + name.split(".")[-1]: c.pixels
            for part in exr.parts
            for name, c in part.channels.items()
        }
    after_rgba = np.stack([channels[f"Combined.{k}"] for k in "RGBA"], -1)
    assert np.allclose(after_rgba, before["Combined"], rtol=1e-5, atol=1e-5)  # float32 rounding between processes
    assert np.allclose(channels["Depth.Z"], before["Depth"], rtol=1e-5, atol=1e-5)
