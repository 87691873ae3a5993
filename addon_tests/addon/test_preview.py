"""Live preview: the extracted mesh follows the cage's modifiers through its embedding, per frame."""

import numpy as np

from blender_nerf_deform.engine.geometry.cage import box_cage
from blender_nerf_deform.engine.geometry.embedding import embed_points


def _nerf_with_cage_and_surface(bpy):
    from blender_nerf_deform.addon.data.cage_store import store_cage, store_embedding

    scene = bpy.context.scene
    nerf = bpy.data.objects.new("NeRF", None)
    nerf.nerf_deform.role = "NERF"
    scene.collection.objects.link(nerf)

    rest, tets = box_cage((3, 3, 6), lo=(-0.5, -0.5, -1.0), hi=(0.5, 0.5, 1.0))
    cage_mesh = bpy.data.meshes.new("Cage")
    store_cage(cage_mesh, rest, tets)
    cage = bpy.data.objects.new("Cage", cage_mesh)
    cage.nerf_deform.role = "CAGE"
    cage.parent = nerf
    scene.collection.objects.link(cage)

    rng = np.random.default_rng(0)
    points = rng.uniform((-0.4, -0.4, -0.9), (0.4, 0.4, 0.9), (200, 3))
    surface_mesh = bpy.data.meshes.new("Surface")
    surface_mesh.from_pydata(points.tolist(), [], [])
    embedding = embed_points(points, rest, tets)
    assert embedding.n_outside == 0
    store_embedding(surface_mesh, embedding.tet_ids, embedding.weights)
    surface = bpy.data.objects.new("Surface", surface_mesh)
    surface.nerf_deform.role = "SURFACE"
    surface.parent = nerf
    scene.collection.objects.link(surface)

    s = nerf.nerf_deform
    s.cage, s.surface, s.deformation_mode = cage, surface, "MODIFIERS"
    return nerf, cage, surface, embedding, points


def _preview(surface):
    key = surface.data.shape_keys.key_blocks["NeRF Deform"]
    co = np.empty(3 * len(key.data), dtype=np.float32)
    key.data.foreach_get("co", co)
    return co.reshape(-1, 3)


def test_cage_modifier_drives_the_surface_preview_per_frame(addon):
    bpy = addon
    from blender_nerf_deform.addon.data.cage_store import evaluated_cage_vertices

    nerf, cage, surface, embedding, points = _nerf_with_cage_and_surface(bpy)
    twist = cage.modifiers.new("Twist", "SIMPLE_DEFORM")
    twist.deform_method, twist.deform_axis = "TWIST", "Z"
    twist.angle = 0.0
    twist.keyframe_insert("angle", frame=1)
    twist.angle = 1.5
    twist.keyframe_insert("angle", frame=10)

    scene = bpy.context.scene
    scene.frame_set(1)
    assert np.allclose(_preview(surface), points, atol=1e-5)  # no twist yet: the rest shape

    scene.frame_set(10)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    expected = embedding.apply(evaluated_cage_vertices(cage, depsgraph))
    got = _preview(surface)
    assert np.allclose(got, expected, atol=1e-5)
    assert np.abs(got - points).max() > 0.2  # it really moved
    # The mesh's own vertices stay the rest shape.
    co = np.empty(3 * len(surface.data.vertices), dtype=np.float32)
    surface.data.vertices.foreach_get("co", co)
    assert np.allclose(co.reshape(-1, 3), points, atol=1e-6)


def test_moving_the_cage_modifier_updates_the_preview_without_a_frame_change(addon):
    bpy = addon
    nerf, cage, surface, embedding, points = _nerf_with_cage_and_surface(bpy)
    bend = cage.modifiers.new("Bend", "SIMPLE_DEFORM")
    bend.deform_method, bend.angle = "BEND", 0.0
    bpy.context.view_layer.update()
    before = _preview(surface).copy()
    bend.angle = 1.0
    bpy.context.view_layer.update()
    assert np.abs(_preview(surface) - before).max() > 0.05
