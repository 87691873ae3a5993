"""Composite With Scene: the NeRF and the scene's meshes (Cycles) merged by depth in the compositor.

- A cube through the NeRF sphere, half in front of its surface, half behind: the composite shows
  the cube where its depth is nearer and the NeRF where the NeRF's is, checked per pixel against
  the two separate renders and their Depth passes; F12 and a fresh `-a` render give that composite.
- The NeRF's Depth pass follows Cycles' convention: Cycles' Depth of a sphere mesh is the analytic
  planar depth (not the distance along the ray), and the NeRF's Depth of the sphere it learnt
  matches it within the thickness of the NeRF's learnt surface (tolerance below).
"""

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from fixtures import REPO
from fixtures.blender_objects import scene_with_nerf

SIZE = 64


def _read_exr(path) -> dict:
    """{channel name without the layer: (H,W) array} of an EXR file (single or multilayer)."""
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as exr:
        return {name.split(".", 1)[-1]: c.pixels.copy() for part in exr.parts for name, c in part.channels.items()}


def _multilayer(scene, path):
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.image_settings.file_format = "OPEN_EXR_MULTILAYER"
    scene.render.filepath = str(path)


def _rgba(channels, prefix=""):
    return np.stack([channels[f"{prefix}{k}"] for k in "RGBA"], -1)


def _interior(mask):
    """`mask` less its pixels next to one outside it (4-neighbours)."""
    padded = np.pad(mask, 1)
    return mask & padded[:-2, 1:-1] & padded[2:, 1:-1] & padded[1:-1, :-2] & padded[1:-1, 2:]


def _emission_material(bpy, color):
    material = bpy.data.materials.new("Emission")
    tree = material.node_tree
    tree.nodes.clear()
    emission, output = tree.nodes.new("ShaderNodeEmission"), tree.nodes.new("ShaderNodeOutputMaterial")
    emission.inputs["Color"].default_value = (*color, 1.0)
    tree.links.new(emission.outputs["Emission"], output.inputs["Surface"])
    return material


def _fast_cycles(mesh_scene):
    """Few samples, no denoiser, samples at the pixel centres (a narrow pixel filter): depth and
    colour of a surface at the pixel centre, as the NeRF's rays are."""
    mesh_scene.cycles.samples = 4
    mesh_scene.cycles.use_denoising = False
    mesh_scene.cycles.filter_width = 0.01


@pytest.mark.slow
def test_a_cube_half_in_front_of_the_nerf_is_merged_by_depth(addon, sphere_nerf, tmp_path):
    bpy = addon
    from mathutils import Euler, Matrix

    from blender_nerf_deform.addon.render.composite import mesh_scene_of

    ckpt, data = sphere_nerf
    meta = json.loads((data / "transforms.json").read_text())
    _nerf, camera = scene_with_nerf(bpy, ckpt, meta["frames"][3], meta["camera_angle_x"], SIZE)
    scene = bpy.context.scene
    # A box (1.8 x 0.6 x 1) turned 34 degrees about the view's up axis, centred 3.1 units in front
    # of the camera (the sphere's centre is at 3): its front edge pokes out of the sphere, its sides
    # go behind it, its right end reaches past the sphere, and the sphere's top and bottom are clear.
    cube = bpy.data.objects.new("Cube", bpy.data.meshes.new("Cube"))
    import bmesh

    shape = bmesh.new()
    bmesh.ops.create_cube(shape, size=1.0)
    shape.to_mesh(cube.data)
    shape.free()
    cube.data.materials.append(_emission_material(bpy, (0.0, 1.0, 0.0)))
    scene.collection.objects.link(cube)
    cube.matrix_world = camera.matrix_world @ Matrix.LocRotScale(
        (0.25, 0.0, -3.1), Euler((0.0, 0.6, 0.0)), (1.8, 0.6, 1.0)
    )

    assert bpy.ops.nerf_deform.composite_with_scene() == {"FINISHED"}
    mesh_scene = mesh_scene_of(scene)
    assert mesh_scene.render.engine == "CYCLES" and mesh_scene.background_set == scene
    assert scene.compositing_node_group is not None and scene.render.use_compositing
    _fast_cycles(mesh_scene)

    # The composite, as F12 renders it.
    scene.render.image_settings.media_type = "IMAGE"
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = str(tmp_path / "composite.exr")
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    composite = _rgba(_read_exr(tmp_path / "composite.exr"))

    # The two renders on their own: the NeRF (compositor off) and the meshes scene.
    scene.render.use_compositing = False
    _multilayer(scene, tmp_path / "nerf.exr")
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    _multilayer(mesh_scene, tmp_path / "meshes.exr")
    assert bpy.ops.render.render(write_still=True, scene=mesh_scene.name) == {"FINISHED"}
    scene.render.use_compositing = True
    nerf, meshes = _read_exr(tmp_path / "nerf.exr"), _read_exr(tmp_path / "meshes.exr")
    nerf_rgba, mesh_rgba = _rgba(nerf, "Combined."), _rgba(meshes, "Combined.")
    nerf_depth, mesh_depth = nerf["Depth.Z"], meshes["Depth.Z"]

    # Z Combine's anti-aliasing blends the two across the edges where the nearer one changes (the
    # cube's outline, the line where it enters the sphere): compared inside each region.
    both = (nerf_rgba[..., 3] > 0.99) & (mesh_rgba[..., 3] > 0.99)
    cube_nearer = _interior(both & (mesh_depth < nerf_depth - 0.02))
    nerf_nearer = _interior(both & (nerf_depth < mesh_depth - 0.02))
    assert cube_nearer.sum() > 80 and nerf_nearer.sum() > 80  # the box is half in front, half behind
    assert np.abs(composite[cube_nearer] - mesh_rgba[cube_nearer]).max() < 0.02
    assert np.abs(composite[nerf_nearer] - nerf_rgba[nerf_nearer]).max() < 0.02
    # Where only one of them is, it shows; where neither is, nothing.
    only_nerf = _interior((nerf_rgba[..., 3] > 0.99) & (mesh_rgba[..., 3] < 1e-3))
    only_cube = _interior((mesh_rgba[..., 3] > 0.99) & (nerf_rgba[..., 3] < 1e-3))
    assert only_nerf.sum() > 100 and only_cube.sum() > 30
    assert np.abs(composite[only_nerf] - nerf_rgba[only_nerf]).max() < 0.02
    assert np.abs(composite[only_cube] - mesh_rgba[only_cube]).max() < 0.02
    empty = _interior((nerf_rgba[..., 3] < 1e-6) & (mesh_rgba[..., 3] < 1e-6))
    assert empty.sum() > 100 and np.abs(composite[empty]).max() < 1e-3

    # Saved and rendered as a farm would (`blender -b shot.blend -a`): the same composite.
    scene.frame_start = scene.frame_end = 1
    scene.render.image_settings.media_type = "IMAGE"
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = str(tmp_path / "farm_")
    blend = tmp_path / "shot.blend"
    assert bpy.ops.wm.save_as_mainfile(filepath=str(blend)) == {"FINISHED"}
    script = f"""
    import bpy, blender_nerf_deform
    blender_nerf_deform.register()
    bpy.ops.wm.open_mainfile(filepath={str(blend)!r})
    assert bpy.ops.render.render(animation=True) == {{"FINISHED"}}
    """
    proc = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(script)], cwd=REPO, capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    farm = _rgba(_read_exr(tmp_path / "farm_0001.exr"))
    assert np.abs(farm - composite).max() < 1e-4


def _sphere_planar_depth(pinhole, center, radius, planar=True):
    """Exact depth of a sphere per pixel centre: planar (along the camera's axis) or along the ray."""
    c2w = np.asarray(pinhole.camera_to_world)
    i = np.arange(pinhole.width) + 0.5
    j = np.arange(pinhole.height) + 0.5
    jj, ii = np.meshgrid(j, i, indexing="ij")
    d_cam = np.stack([(ii - pinhole.cx) / pinhole.fx, -(jj - pinhole.cy) / pinhole.fy, -np.ones_like(ii)], -1)
    d = d_cam @ c2w[:3, :3].T  # planar depth 1 per unit of t
    o = c2w[:3, 3] - np.asarray(center)
    a, b, c = (d * d).sum(-1), (d @ o), o @ o - radius**2
    disc = b * b - a * c
    t = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / a, np.nan)
    return t if planar else t * np.linalg.norm(d, axis=-1)


@pytest.mark.slow
def test_the_nerf_depth_pass_is_cycles_depth_of_the_same_surface(addon, sphere_nerf, tmp_path):
    bpy = addon
    from fixtures.sphere_data import RADIUS
    from mathutils import Euler, Matrix

    from blender_nerf_deform.addon.data.camera import pinhole_from_blender
    from blender_nerf_deform.addon.render.composite import mesh_scene_of

    ckpt, data = sphere_nerf
    meta = json.loads((data / "transforms.json").read_text())
    # The NeRF placed, turned and scaled 1.5x, the camera keeping its training view of it: depths in
    # world units are 1.5x the NeRF's own.
    scale = 1.5
    placement = Matrix.LocRotScale((1.0, 2.0, 0.5), Euler((0.2, -0.3, 0.9)), (scale, scale, scale))
    nerf, camera = scene_with_nerf(bpy, ckpt, meta["frames"][7], meta["camera_angle_x"], SIZE, placement)
    camera.matrix_world = camera.matrix_world @ Matrix.Scale(1 / scale, 4)  # a unit-scale camera
    scene = bpy.context.scene
    center, radius = (1.0, 2.0, 0.5), RADIUS * scale
    bpy.ops.mesh.primitive_uv_sphere_add(radius=radius, segments=256, ring_count=128, location=center)
    assert bpy.ops.nerf_deform.composite_with_scene() == {"FINISHED"}
    mesh_scene = mesh_scene_of(scene)
    _fast_cycles(mesh_scene)
    scene.render.use_compositing = False
    _multilayer(scene, tmp_path / "nerf.exr")
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    _multilayer(mesh_scene, tmp_path / "meshes.exr")
    assert bpy.ops.render.render(write_still=True, scene=mesh_scene.name) == {"FINISHED"}
    nerf_pass, cycles = _read_exr(tmp_path / "nerf.exr"), _read_exr(tmp_path / "meshes.exr")

    bpy.context.view_layer.update()
    pinhole = pinhole_from_blender(scene, camera)
    planar = _sphere_planar_depth(pinhole, center, radius)
    along_ray = _sphere_planar_depth(pinhole, center, radius, planar=False)
    # Pixels whose neighbours all see the sphere too: away from the rim, where depth changes fast.
    inside = _interior(np.isfinite(planar)) & (cycles["Combined.A"] > 0.999) & (nerf_pass["Combined.A"] > 0.99)
    assert inside.sum() > 300

    # Cycles' Depth is the planar depth (measured within 0.0005 of the analytic sphere);
    # the depth along the ray differs from it by up to 0.13 here, so the two are told apart.
    assert np.abs(cycles["Depth.Z"][inside] - planar[inside]).max() < 3e-3
    assert np.abs(along_ray[inside] - planar[inside]).max() > 0.03

    # The NeRF's Depth is its expected termination distance, which lies in its learnt density shell:
    # behind a hard surface by part of the shell's thickness. The fixture's NeRF learnt from 32-pixel
    # images, one pixel 0.09 units wide at the sphere (0.135 here at 1.5x): its shell is a few pixels
    # thick. Measured on this view: median 0.075, 95th percentile 0.15, at most 0.21 (NeRF units);
    # allowed: median within 2 pixel widths, 95th percentile within 3, all within 4.
    pixel = scale * 3.0 * 2 * np.tan(0.5 * meta["camera_angle_x"]) / meta["w"]
    difference = nerf_pass["Depth.Z"][inside] - cycles["Depth.Z"][inside]
    assert 0 <= np.median(difference) < 2 * pixel
    assert np.percentile(np.abs(difference), 95) < 3 * pixel
    assert np.abs(difference).max() < 4 * pixel


def test_composite_with_scene_again_rebuilds_its_own_setup_and_keeps_the_artists(addon):
    bpy = addon
    from blender_nerf_deform.addon.render.composite import TREE_NAME, mesh_scene_of

    scene = bpy.context.scene
    nerf = bpy.data.objects.new("NeRF", None)
    nerf.nerf_deform.role = "NERF"
    scene.collection.objects.link(nerf)
    with pytest.raises(RuntimeError, match="Composite With Scene: scene 'Scene' has no active camera"):
        bpy.ops.nerf_deform.composite_with_scene()
    assert mesh_scene_of(scene) is None and len(bpy.data.scenes) == 1

    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(camera)
    scene.camera = camera
    artists = bpy.data.node_groups.new("Artist's grade", "CompositorNodeTree")
    scene.compositing_node_group = artists
    assert bpy.ops.nerf_deform.composite_with_scene() == {"FINISHED"}
    mesh_scene = mesh_scene_of(scene)
    assert mesh_scene.camera == camera and mesh_scene.background_set == scene
    assert scene.compositing_node_group.name == TREE_NAME and artists.use_fake_user
    assert scene.view_layers[0].use_pass_z and mesh_scene.view_layers[0].use_pass_z

    # The artist switches camera and resolution, and runs it again: the same meshes scene, in step.
    other = bpy.data.objects.new("Other", bpy.data.cameras.new("Other"))
    scene.collection.objects.link(other)
    scene.camera, scene.render.resolution_x = other, 333
    assert bpy.ops.nerf_deform.composite_with_scene(engine="BLENDER_EEVEE") == {"FINISHED"}
    assert mesh_scene_of(scene) == mesh_scene and len(bpy.data.scenes) == 2
    assert mesh_scene.camera == other and mesh_scene.render.resolution_x == 333
    assert mesh_scene.render.engine == "BLENDER_EEVEE"
    assert [g.name for g in bpy.data.node_groups if g.get("nerf_deform_composite")] == [TREE_NAME]
    tree = scene.compositing_node_group
    assert {n.bl_idname for n in tree.nodes} == {"CompositorNodeRLayers", "CompositorNodeZcombine", "NodeGroupOutput"}
    assert {n.scene for n in tree.nodes if n.bl_idname == "CompositorNodeRLayers"} == {scene, mesh_scene}

    # Run on the meshes scene by mistake: told where to run it.
    from blender_nerf_deform.addon.render.composite import composite_with_scene

    with pytest.raises(ValueError, match="is the meshes scene of 'Scene': run Composite With Scene in 'Scene'"):
        composite_with_scene(mesh_scene)
