"""Extract Mesh through bpy.ops on a trained NeRF, then Build Cage on what it extracted."""

import numpy as np
import pytest
from fixtures.sphere_data import RADIUS


@pytest.mark.slow
def test_extract_mesh_then_build_cage(addon, sphere_nerf):
    bpy = addon
    from blender_nerf_deform.addon.edit.extract import COLOR_ATTRIBUTE

    ckpt, _ = sphere_nerf
    assert bpy.ops.nerf_deform.load_nerf(filepath=str(ckpt)) == {"FINISHED"}
    nerf = bpy.context.active_object
    nerf.nerf_deform.resolution = 48
    assert bpy.ops.nerf_deform.extract_mesh() == {"FINISHED"}
    surface = nerf.nerf_deform.surface
    assert surface.parent == nerf and surface.nerf_deform.role == "SURFACE" and surface.hide_render
    co = np.empty(3 * len(surface.data.vertices), dtype=np.float32)
    surface.data.vertices.foreach_get("co", co)
    radius = np.linalg.norm(co.reshape(-1, 3), axis=1)
    assert len(surface.data.polygons) > 100
    assert abs(np.median(radius) - RADIUS) < 0.15  # the analytic sphere the NeRF learnt
    colors = np.empty(4 * len(surface.data.vertices), dtype=np.float32)
    surface.data.color_attributes[COLOR_ATTRIBUTE].data.foreach_get("color", colors)
    assert colors.reshape(-1, 4)[:, :3].std(axis=0).min() > 0.02  # coloured by the NeRF, not flat

    bpy.context.view_layer.objects.active = nerf
    assert bpy.ops.nerf_deform.build_cage() == {"FINISHED"}
    assert nerf.nerf_deform.cage is not None
    with pytest.raises(RuntimeError, match="already has a cage or handles"):
        bpy.ops.nerf_deform.extract_mesh()


def test_extract_with_a_threshold_above_every_density_says_so(addon, sphere_nerf):
    bpy = addon
    ckpt, _ = sphere_nerf
    bpy.ops.nerf_deform.load_nerf(filepath=str(ckpt))
    nerf = bpy.context.active_object
    nerf.nerf_deform.resolution, nerf.nerf_deform.threshold = 24, 1e9
    with pytest.raises(RuntimeError, match="the density grid is empty"):
        bpy.ops.nerf_deform.extract_mesh()
    assert nerf.nerf_deform.surface is None and len(bpy.data.objects) == 1
