"""The add-on's Python API (addon/api.py): the pipeline from a script, as the buttons run it."""

import numpy as np
import pytest


@pytest.mark.slow
def test_a_script_edits_the_lower_half_of_the_sphere(addon, sphere_nerf):
    bpy = addon
    from blender_nerf_deform.addon import api
    from blender_nerf_deform.addon.data.cage_store import cage_pins, load_cage
    from blender_nerf_deform.addon.deform import poses as deformation
    from blender_nerf_deform.addon.worker import jobs

    ckpt, _ = sphere_nerf
    nerf = api.load(ckpt)
    region = api.add_edit_region(nerf, center=(0.0, 0.0, -0.4), size=(2.0, 2.0, 0.8))
    assert region.parent == nerf and tuple(region.scale) == pytest.approx((2.0, 2.0, 0.8))
    surface = api.extract(nerf, resolution=48)
    co = np.array([v.co[:] for v in surface.data.vertices])
    assert co[:, 2].max() < 0.06  # the region's top at z = 0 cut the sphere
    cage = api.build_cage(nerf)
    pins = cage_pins(cage)
    assert len(pins) > 0
    bottom = api.vertices_near(surface, (0.0, 0.0, -0.8), 0.35)
    handle = api.add_handle(nerf, bottom)
    assert handle.nerf_deform.role == "HANDLE" and surface.mode == "OBJECT"
    handle.location.z -= 0.3
    bpy.context.view_layer.update()
    rest, _tets = load_cage(cage.data)
    moved = deformation.deformed_cage(nerf, bpy.context.evaluated_depsgraph_get(), jobs.worker(bpy.context))
    # The cut stays (soft pins: within a thousandth of the cage's size).
    assert np.linalg.norm(moved[pins] - rest[pins], axis=1).max() < 1e-3 * np.linalg.norm(np.ptp(rest, axis=0))
    assert (rest[:, 2] - moved[:, 2]).max() > 0.2  # the bottom went down
    with pytest.raises(RuntimeError, match="is not a vertex of"):
        api.add_handle(nerf, [len(surface.data.vertices) + 5])
    assert surface.mode == "OBJECT"
    with pytest.raises(RuntimeError, match="is not a NeRF object"):
        api.extract(bpy.data.objects.new("Plain", None))
