"""The "NeRF Objects" sub-panel's facts (scene_panel.nerf_status): visibility, regions, mesh, cage, staleness."""

import pytest
from fixtures.blender_objects import nerf_with_sphere_surface


@pytest.mark.slow
def test_status_follows_visibility_regions_mesh_and_cage(addon):
    bpy = addon
    from blender_nerf_deform.addon.ui.scene_panel import NERFDEFORM_PT_scene_nerfs, nerf_status, scene_nerfs

    layer = bpy.context.view_layer
    assert not NERFDEFORM_PT_scene_nerfs.poll(bpy.context)
    nerf, surface = nerf_with_sphere_surface(bpy)
    nerf.nerf_deform.aabb = (-1.5, -1.5, -1.5, 1.5, 1.5, 1.5)
    other = bpy.data.objects.new("Other NeRF", None)
    other.nerf_deform.role = "NERF"
    bpy.context.scene.collection.objects.link(other)
    assert [o.name for o in scene_nerfs(bpy.context.scene)] == ["NeRF", "Other NeRF"]
    assert NERFDEFORM_PT_scene_nerfs.poll(bpy.context)

    st = nerf_status(other, layer)
    assert st["in_viewport"] and st["in_render"] and st["regions"] == [] and st["cage_tets"] == 0
    assert st["stale"] == ["no mesh yet: Extract Mesh, then Build Cage"]
    st = nerf_status(nerf, layer)
    assert st["surface_vertices"] == len(surface.data.vertices) and st["stale"] == ["no cage yet: Build Cage"]

    bpy.context.view_layer.objects.active = nerf
    assert bpy.ops.nerf_deform.build_cage() == {"FINISHED"}
    st = nerf_status(nerf, layer)
    assert st["cage_tets"] > 10 and st["cage_pieces"] == 1 and st["stale"] == []

    # Visibility: each switch the depsgraphs honour.
    other.hide_render = True
    assert not nerf_status(other, layer)["in_render"] and nerf_status(other, layer)["in_viewport"]
    other.hide_render = False
    other.hide_set(True)
    assert not nerf_status(other, layer)["in_viewport"] and nerf_status(other, layer)["in_render"]
    other.hide_set(False)
    hidden = bpy.data.collections.new("Hidden")
    bpy.context.scene.collection.children.link(hidden)
    bpy.context.scene.collection.objects.unlink(other)
    hidden.objects.link(other)
    layer.layer_collection.children["Hidden"].exclude = True
    st = nerf_status(other, layer)
    assert not st["in_viewport"] and not st["in_render"]
    layer.layer_collection.children["Hidden"].exclude = False
    hidden.hide_render = True
    st = nerf_status(other, layer)
    assert st["in_viewport"] and not st["in_render"]

    # A region added after the extraction, and a mesh edited after the cage: both said.
    assert bpy.ops.nerf_deform.add_edit_region() == {"FINISHED"}
    region = [o for o in bpy.data.objects if o.nerf_deform.role == "REGION"][0]
    st = nerf_status(nerf, layer)
    assert st["regions"] == [region.name]
    assert any("regions changed" in line for line in st["stale"])
    import bmesh

    bm = bmesh.new()
    bm.from_mesh(surface.data)
    bmesh.ops.subdivide_edges(bm, edges=bm.edges[:4], cuts=1)
    bm.to_mesh(surface.data)
    bm.free()
    assert any("Build Cage again" in line for line in nerf_status(nerf, layer)["stale"])

    assert bpy.ops.nerf_deform.activate_nerf(name="Other NeRF") == {"FINISHED"}
    assert bpy.context.view_layer.objects.active == other and other.select_get()
    with pytest.raises(RuntimeError, match="no NeRF object 'Nope'"):
        bpy.ops.nerf_deform.activate_nerf(name="Nope")
