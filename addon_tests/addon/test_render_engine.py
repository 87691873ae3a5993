"""The NeRF Deform RenderEngine renders what the engine renders, from Blender's camera and placement."""

import json

import numpy as np
import pytest
from fixtures.blender_objects import engine_render, render_exr_passes, scene_with_nerf
from PIL import Image

from blender_nerf_deform.engine.nerf.substeps import FINAL_SUBSTEPS


@pytest.mark.slow
@pytest.mark.parametrize("placed", [False, True], ids=["at_origin", "moved_rotated_scaled"])
def test_f12_matches_the_engine_cli_render(addon, sphere_nerf, tmp_path, placed):
    bpy = addon
    ckpt, data = sphere_nerf
    meta = json.loads((data / "transforms.json").read_text())
    frame = meta["frames"][3]
    one = {**meta, "frames": [frame]}
    (tmp_path / "one.json").write_text(json.dumps(one))
    engine_render(ckpt, tmp_path / "one.json", tmp_path / "cli")
    name = frame["file_path"].rsplit("/", 1)[-1].rsplit(".", 1)[0]
    expected = np.asarray(Image.open(tmp_path / "cli" / f"{name}.png").convert("RGBA"), dtype=np.int16)

    placement = None
    if placed:  # the NeRF object moved, turned and scaled; the camera keeps its view of it
        from mathutils import Euler, Matrix

        placement = Matrix.LocRotScale((2.0, -1.0, 0.5), Euler((0.3, -0.2, 1.1)), (1.7, 1.7, 1.7))
    scene_with_nerf(bpy, ckpt, frame, meta["camera_angle_x"], meta["w"], placement)
    bpy.context.scene.render.filepath = str(tmp_path / "blender.png")
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    got = np.asarray(Image.open(tmp_path / "blender.png").convert("RGBA"), dtype=np.int16)

    assert got.shape == expected.shape
    assert expected[..., 3].max() > 120 and expected[..., 3].min() < 20  # both the NeRF and empty space are in view
    # Same pixels, rows the right way up; 8-bit rounding through Blender's colour pipeline aside.
    visible = expected[..., 3] > 8
    assert np.abs(got[..., 3] - expected[..., 3]).max() <= 2
    assert np.abs(got[..., :3] - expected[..., :3])[visible].max() <= 3


@pytest.mark.slow
def test_depth_is_planar_world_distance_and_alpha_is_coverage(addon, sphere_nerf, tmp_path):
    bpy = addon
    from mathutils import Euler, Matrix

    from blender_nerf_deform.addon.worker import jobs

    ckpt, data = sphere_nerf
    meta = json.loads((data / "transforms.json").read_text())
    # A wide lens, so that rays near the corners miss the NeRF's box: nothing there at all.
    frame, size, angle = meta["frames"][5], meta["w"], 2.4
    nerf, _ = scene_with_nerf(bpy, ckpt, frame, angle, size)
    plain = render_exr_passes(bpy, tmp_path / "plain.exr")
    assert np.allclose(plain["Alpha"], plain["Combined"][..., 3])
    hit = plain["Alpha"] > 1e-6
    assert hit.any() and (~hit).any()
    assert np.all(plain["Depth"][~hit] == 1e10)

    # Planar depth = distance along the unit ray / length of the pixel's camera-space ray with z = -1.
    f = 0.5 * size / np.tan(0.5 * angle)
    centres = np.arange(size) + 0.5
    jj, ii = np.meshgrid(centres, centres, indexing="ij")
    ray_length = np.sqrt(((ii - size / 2) / f) ** 2 + ((jj - size / 2) / f) ** 2 + 1.0)
    camera = {
        "width": size,
        "height": size,
        "fx": f,
        "fy": f,
        "cx": size / 2,
        "cy": size / 2,
        "camera_to_world": frame["transform_matrix"],
    }
    # F12 marches the NeRF's Render Substeps (default: the engine's final-frame substeps); the worker's
    # render op one unless asked.
    assert nerf.nerf_deform.render_substeps == FINAL_SUBSTEPS
    _, out = jobs.worker(bpy.context).call(
        "render", {"checkpoint": str(ckpt), "camera": camera, "substeps": FINAL_SUBSTEPS}
    )
    assert np.allclose(plain["Depth"][hit], (out["depth"] / ray_length)[hit], rtol=1e-4)

    # The NeRF scaled 2x (and moved, turned) with the camera keeping its view: same picture, twice the depth.
    placement = Matrix.LocRotScale((1.0, 2.0, -0.5), Euler((0.2, 0.4, -0.7)), (2.0, 2.0, 2.0))
    nerf.matrix_world = placement
    bpy.context.scene.camera.matrix_world = placement @ Matrix(frame["transform_matrix"]) @ Matrix.Scale(0.5, 4)
    scaled = render_exr_passes(bpy, tmp_path / "scaled.exr")
    # Blender composes object matrices in float32, so the rays move by ~1e-7 and a fixed-step
    # march samples slightly different points: equal up to that, not bit for bit.
    assert np.allclose(scaled["Combined"], plain["Combined"], atol=1e-2)
    assert np.allclose(scaled["Depth"][hit], 2.0 * plain["Depth"][hit], rtol=1e-2)


def test_render_without_a_nerf_is_a_clear_error(addon, tmp_path):
    bpy = addon
    scene = bpy.context.scene
    scene.render.engine = "NERF_DEFORM"
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(camera)
    scene.camera = camera
    with pytest.raises(RuntimeError, match="no NeRF object in the scene to render: use Load NeRF first"):
        bpy.ops.render.render()


def test_orthographic_camera_is_refused_by_the_render(addon, sphere_nerf):
    bpy = addon
    ckpt, data = sphere_nerf
    meta = json.loads((data / "transforms.json").read_text())
    _, camera = scene_with_nerf(bpy, ckpt, meta["frames"][0], meta["camera_angle_x"], 16)
    camera.data.type = "ORTHO"
    with pytest.raises(RuntimeError, match="'Camera' is orthographic"):
        bpy.ops.render.render()


@pytest.mark.slow
def test_moving_the_cage_in_cage_modifiers_mode_renders_like_moving_the_camera_back(addon, sphere_nerf, tmp_path):
    bpy = addon
    from mathutils import Matrix, Vector

    from blender_nerf_deform.addon.data.cage_store import store_cage
    from blender_nerf_deform.engine.geometry.cage import box_cage

    ckpt, data = sphere_nerf
    meta = json.loads((data / "transforms.json").read_text())
    nerf, camera = scene_with_nerf(bpy, ckpt, meta["frames"][4], meta["camera_angle_x"], meta["w"])
    rest, tets = box_cage((4, 4, 4), lo=(-1.5, -1.5, -1.5), hi=(1.5, 1.5, 1.5))
    cage = bpy.data.objects.new("Cage", bpy.data.meshes.new("Cage"))
    store_cage(cage.data, rest, tets)
    cage.nerf_deform.role = "CAGE"
    bpy.context.scene.collection.objects.link(cage)
    cage.parent = nerf
    nerf.nerf_deform.cage, nerf.nerf_deform.deformation_mode = cage, "MODIFIERS"

    def render(name):
        bpy.context.scene.render.filepath = str(tmp_path / name)
        assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
        return np.asarray(Image.open(tmp_path / name).convert("RGBA"), dtype=np.float64) / 255

    still = render("still.png")
    shift = Vector((0.3, -0.2, 0.25))
    cage.location = shift
    moved_content = render("moved_content.png")
    cage.location = (0, 0, 0)
    camera.matrix_world = Matrix.Translation(-shift) @ camera.matrix_world
    moved_camera = render("moved_camera.png")

    from fixtures import psnr as _psnr

    assert _psnr(moved_content, moved_camera) >= 35  # 8-bit PNGs of a bent render vs a plain one
    assert _psnr(moved_content, still) < _psnr(moved_content, moved_camera) - 10


def test_a_mirrored_handle_and_folds_are_each_reported_in_one_line(addon):
    """The worker's answer for a frame names a mirrored handle (surface ARAP cannot mirror without a
    fold) and any folded tets (Cage Modifiers can fold); F12 reports each as one warning line."""
    from blender_nerf_deform.addon.render.frame import render_warnings

    mirrored, folded = render_warnings("Fox", 7, {"reflected_handles": ["Tail"], "inverted_tets": 3})
    assert "Fox, frame 7" in mirrored and "Tail mirrors its region" in mirrored and "positive scale" in mirrored
    assert "3 inverted" in folded and "\n" not in mirrored + folded
    assert render_warnings("Fox", 1, {"min_det_f": 0.4, "surface_residual": 0.01}) == []
