"""Edit regions from the add-on: the box Empty and its REGION dict, Extract Mesh inside it (the cut
flagged), Build Cage pinned at the cut, ARAP keeping the pins, and the errors of bad regions and
picks. Real headless Blender and the real worker."""

from __future__ import annotations

import math

import numpy as np
import pytest

from test_handles import _select_in_edit_mode

BOX = (-1.5, -1.5, -1.5, 1.5, 1.5, 1.5)


def _nerf(bpy, ckpt=None):
    """A NeRF object: loaded from `ckpt`, or (no worker) made as Load NeRF makes it."""
    if ckpt is not None:
        assert bpy.ops.nerf_deform.load_nerf(filepath=str(ckpt)) == {"FINISHED"}
        nerf = bpy.context.active_object
        nerf.nerf_deform.resolution = 48
        return nerf
    nerf = bpy.data.objects.new("NeRF", None)
    nerf.empty_display_type = "CUBE"
    nerf.nerf_deform.role = "NERF"
    nerf.nerf_deform.aabb = BOX
    bpy.context.scene.collection.objects.link(nerf)
    bpy.context.view_layer.objects.active = nerf
    return nerf


def _add_region(bpy, nerf):
    bpy.context.view_layer.objects.active = nerf
    assert bpy.ops.nerf_deform.add_edit_region() == {"FINISHED"}
    region = nerf.nerf_deform.edit_region
    assert region is not None and bpy.context.active_object == region
    return region


def _place(bpy, region, center, size, euler=(0.0, 0.0, 0.0)):
    region.location = center
    region.rotation_euler = euler
    region.scale = [s / (2 * region.empty_display_size) for s in size]
    bpy.context.view_layer.update()


def _co(mesh):
    co = np.empty(3 * len(mesh.vertices), dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    return co.reshape(-1, 3).astype(np.float64)


def test_add_edit_region_makes_a_box_empty_whose_region_follows_its_transform(addon):
    bpy = addon
    from mathutils import Matrix, Vector

    from blender_nerf_deform.addon.region_ops import edit_region_of
    from blender_nerf_deform.engine.geometry.region import region_from_dict

    nerf = _nerf(bpy)
    # The NeRF placed, turned and scaled in the scene: the region is in the NeRF's own frame.
    nerf.matrix_world = Matrix.Translation((0.5, -0.25, 0.2)) @ Matrix.Rotation(0.5, 4, "Z") @ Matrix.Scale(2.0, 4)
    bpy.context.view_layer.update()
    bpy.context.scene.cursor.location = nerf.matrix_world @ Vector((0.3, -0.6, 0.9))
    region = _add_region(bpy, nerf)
    assert region.type == "EMPTY" and region.empty_display_type == "CUBE"
    assert region.parent == nerf and region.nerf_deform.role == "REGION" and region.nerf_deform.nerf == nerf
    assert np.allclose(np.array(region.matrix_parent_inverse), np.eye(4))
    bpy.context.view_layer.update()
    d = edit_region_of(nerf)  # around the cursor (inside the box), a third of the box
    assert np.allclose(d["center"], [0.3, -0.6, 0.9], atol=1e-5)
    assert np.allclose(d["size"], [1.0, 1.0, 1.0], atol=1e-6) and np.allclose(d["rotation_euler"], 0, atol=1e-7)

    # Moved, rotated and scaled by the artist (and its display size changed): the numbers the engine gets.
    euler = (0.3, -0.2, 0.5)
    region.location, region.rotation_euler, region.scale = (0.1, 0.2, 0.3), euler, (0.4, 0.6, 0.8)
    region.empty_display_size = 1.0
    bpy.context.view_layer.update()
    d = edit_region_of(nerf)
    assert np.allclose(d["center"], [0.1, 0.2, 0.3], atol=1e-5)
    assert np.allclose(d["size"], [0.8, 1.2, 1.6], atol=1e-5)  # 2 * display size * scale
    assert np.allclose(d["rotation_euler"], euler, atol=1e-5)
    # The engine's box has the Empty's corners, in the NeRF's frame.
    corner_local = np.array([1.0, -1.0, 1.0])  # a corner of the unit cube the Empty draws (display size 1)
    corner_nerf = np.array(nerf.matrix_world.inverted() @ region.matrix_world @ Vector(corner_local))
    box = region_from_dict(d)
    assert np.allclose(box.to_world(corner_local * box.half), corner_nerf, atol=1e-5)

    # A second Add Edit Region selects the region it has.
    bpy.context.view_layer.objects.active = nerf
    n_objects = len(bpy.data.objects)
    assert bpy.ops.nerf_deform.add_edit_region() == {"FINISHED"}
    assert len(bpy.data.objects) == n_objects and bpy.context.active_object == region


def test_a_new_region_with_the_cursor_outside_the_box_covers_the_whole_box(addon):
    bpy = addon
    from blender_nerf_deform.addon.region_ops import edit_region_of

    nerf = _nerf(bpy)
    nerf.nerf_deform.aabb = (-1.0, -2.0, 0.0, 3.0, 2.0, 1.0)
    bpy.context.scene.cursor.location = (5.0, 0.0, 0.0)
    _add_region(bpy, nerf)
    bpy.context.view_layer.update()
    d = edit_region_of(nerf)
    assert np.allclose(d["center"], [1.0, 0.0, 0.5], atol=1e-6) and np.allclose(d["size"], [4.0, 4.0, 1.0], atol=1e-5)


def test_regions_without_a_box_are_refused_before_anything_is_extracted(addon):
    bpy = addon
    nerf = _nerf(bpy)  # no checkpoint: the region is checked before the worker is asked anything
    region = _add_region(bpy, nerf)
    n_objects = len(bpy.data.objects)

    region.scale = (1.0, 0.0, 1.0)
    bpy.context.view_layer.update()
    bpy.context.view_layer.objects.active = nerf
    with pytest.raises(RuntimeError, match=f"edit region '{region.name}' has zero size"):
        bpy.ops.nerf_deform.extract_mesh()
    assert nerf.nerf_deform.surface is None and len(bpy.data.objects) == n_objects

    # Skewed: under a parent with a non-uniform scale, turned 45 degrees in it.
    stretch = bpy.data.objects.new("Stretch", None)
    bpy.context.scene.collection.objects.link(stretch)
    stretch.parent, stretch.scale = nerf, (1.0, 2.0, 1.0)
    region.parent, region.scale, region.rotation_euler = stretch, (1.0, 1.0, 1.0), (0.0, 0.0, math.pi / 4)
    bpy.context.view_layer.update()
    bpy.context.view_layer.objects.active = nerf
    with pytest.raises(RuntimeError, match=f"edit region '{region.name}' is skewed"):
        bpy.ops.nerf_deform.extract_mesh()
    assert nerf.nerf_deform.surface is None

    # Mirrored (a negative scale): the same box, taken as it is.
    from blender_nerf_deform.addon.region_ops import edit_region_of

    region.parent, region.rotation_euler, region.scale = nerf, (0.0, 0.0, 0.0), (-0.5, 1.0, 1.0)
    bpy.context.view_layer.update()
    assert np.allclose(edit_region_of(nerf)["size"], [0.5, 1.0, 1.0], atol=1e-6)


def test_a_deleted_region_is_forgotten_and_the_region_survives_save_and_reopen(addon, tmp_path):
    bpy = addon
    from blender_nerf_deform.addon.properties import forget_deleted
    from blender_nerf_deform.addon.region_ops import edit_region_of

    nerf = _nerf(bpy)
    region = _add_region(bpy, nerf)
    _place(bpy, region, (0.2, 0.1, 0.4), (1.0, 0.5, 0.8), (0.1, 0.0, 0.7))
    before = edit_region_of(nerf)
    blend = tmp_path / "region.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    nerf = bpy.data.objects["NeRF"]
    region = nerf.nerf_deform.edit_region
    assert region is not None and region.nerf_deform.role == "REGION" and region.nerf_deform.nerf == nerf
    after = edit_region_of(nerf)
    for key in before:
        assert np.allclose(before[key], after[key], atol=1e-6), key

    # Deleted from the outliner (unlinked): the pointers to it go, and Add Edit Region makes a new one.
    for collection in list(region.users_collection):
        collection.objects.unlink(region)
    forget_deleted()
    assert nerf.nerf_deform.edit_region is None and edit_region_of(nerf) is None
    assert _add_region(bpy, nerf) != region


@pytest.mark.slow
def test_extract_in_a_region_cuts_the_sphere_and_the_cage_is_pinned_at_the_cut(addon, sphere_nerf, tmp_path):
    bpy = addon
    from blender_nerf_deform.addon import jobs
    from blender_nerf_deform.addon.cage_store import CUT_PIN_GROUP, cage_pins, load_cage, load_embedding
    from blender_nerf_deform.addon.deformation import deformed_cage
    from blender_nerf_deform.addon.extract_ops import cut_flags
    from blender_nerf_deform.addon.handles import group_vertices
    from blender_nerf_deform.addon.region_ops import edit_region_of, extracted_region

    ckpt, _ = sphere_nerf
    nerf = _nerf(bpy, ckpt)
    region = _add_region(bpy, nerf)
    # The lower half of the sphere (radius 0.8; the briefly trained NeRF is densest there).
    _place(bpy, region, (0.0, 0.0, -0.4), (2.0, 2.0, 0.8))
    nerf.nerf_deform.pick_object = True
    bpy.context.scene.cursor.location = (0.0, 0.0, -0.6)  # in the sphere, near its bottom
    bpy.context.view_layer.objects.active = nerf
    assert bpy.ops.nerf_deform.extract_mesh() == {"FINISHED"}
    surface = nerf.nerf_deform.surface
    co = _co(surface.data)
    cut = cut_flags(surface.data)
    assert len(surface.data.polygons) > 100 and cut is not None and len(cut) == len(co)
    assert co[:, 2].max() < 0.05 and co[:, 2].min() < -0.6  # the lower half only
    assert cut.sum() > 20 and np.abs(co[cut, 2]).max() < 0.06  # closed (and flagged) along the cut at z = 0
    assert np.abs(co[~cut, 2]).min() < 0.2 and co[~cut, 2].mean() < -0.3
    assert extracted_region(surface) == edit_region_of(nerf)

    bpy.context.view_layer.objects.active = nerf
    assert bpy.ops.nerf_deform.build_cage() == {"FINISHED"}
    cage = nerf.nerf_deform.cage
    rest, tets = load_cage(cage.data)
    pins = cage_pins(cage)
    assert len(pins) > 10 and np.array_equal(np.sort(group_vertices(cage, CUT_PIN_GROUP)), pins)
    # The cage's side at the cut and the rim around it, far from its bottom.
    assert rest[pins, 2].min() > -0.5 and rest[:, 2].min() < -0.8 and np.abs(rest[pins, 2]).mean() < 0.25

    # A handle on the bottom moved down: ARAP keeps the pinned cage vertices at rest, the cut stays.
    bottom = np.flatnonzero(co[:, 2] < -0.6)
    _select_in_edit_mode(bpy, surface, bottom)
    assert bpy.ops.nerf_deform.add_handle() == {"FINISHED"}
    handle = bpy.context.active_object
    handle.location.z -= 0.3
    bpy.context.view_layer.update()
    tet_ids, weights = load_embedding(surface.data)

    def solved():
        deformed = deformed_cage(nerf, bpy.context.evaluated_depsgraph_get(), jobs.worker(bpy.context))
        carried = np.einsum("nk,nkc->nc", weights, deformed[tets[tet_ids]])
        return deformed, carried - co

    deformed, moved = solved()
    assert np.abs(deformed[pins] - rest[pins]).max() < 1e-6
    assert np.allclose(moved[bottom, 2], -0.3, atol=0.03)
    assert np.abs(moved[cut]).max() < 0.05

    # Pin Cut off: no pins, and the whole half sphere follows the handle, cut and all.
    nerf.nerf_deform.pin_cut = False
    bpy.context.view_layer.objects.active = nerf
    assert bpy.ops.nerf_deform.build_cage() == {"FINISHED"}
    assert len(cage_pins(cage)) == 0 and CUT_PIN_GROUP not in cage.vertex_groups
    rest, tets = load_cage(cage.data)
    tet_ids, weights = load_embedding(surface.data)
    _deformed, moved = solved()
    assert np.allclose(moved[bottom, 2], -0.3, atol=0.03) and moved[cut, 2].mean() < -0.2

    # Pinned again, saved and reopened: the cut flags, the pins and the region used are in the file.
    nerf.nerf_deform.pin_cut = True
    bpy.context.view_layer.objects.active = nerf
    assert bpy.ops.nerf_deform.build_cage() == {"FINISHED"}
    pins = cage_pins(cage)
    blend = tmp_path / "cut.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    nerf = next(o for o in bpy.data.objects if o.nerf_deform.role == "NERF")
    assert np.array_equal(cage_pins(nerf.nerf_deform.cage), pins) and len(pins)
    assert np.array_equal(cut_flags(nerf.nerf_deform.surface.data), cut)
    assert extracted_region(nerf.nerf_deform.surface) == edit_region_of(nerf)


@pytest.mark.slow
def test_bad_regions_and_picks_get_the_workers_error_and_leave_the_scene_alone(addon, sphere_nerf):
    bpy = addon
    from blender_nerf_deform.addon.extract_ops import cut_flags
    from blender_nerf_deform.addon.region_ops import extracted_region

    ckpt, _ = sphere_nerf
    nerf = _nerf(bpy, ckpt)
    nerf.nerf_deform.resolution = 32
    region = _add_region(bpy, nerf)
    n_objects = len(bpy.data.objects)

    _place(bpy, region, (3.0, 3.0, 3.0), (0.5, 0.5, 0.5))  # beside the NeRF's box
    bpy.context.view_layer.objects.active = nerf
    with pytest.raises(RuntimeError, match="lies outside the NeRF's box"):
        bpy.ops.nerf_deform.extract_mesh()
    assert nerf.nerf_deform.surface is None and len(bpy.data.objects) == n_objects

    _place(bpy, region, (0.0, 0.0, 0.0), (2.9, 2.9, 2.9))
    nerf.nerf_deform.pick_object = True
    bpy.context.scene.cursor.location = (1.3, 1.3, 1.3)  # in the air beside the sphere
    bpy.context.view_layer.objects.active = nerf
    with pytest.raises(RuntimeError, match="is in empty space"):
        bpy.ops.nerf_deform.extract_mesh()
    assert nerf.nerf_deform.surface is None and len(bpy.data.objects) == n_objects

    # Without its (deleted) region Extract Mesh extracts over the whole box: the whole sphere.
    nerf.nerf_deform.pick_object = False
    for collection in list(region.users_collection):
        collection.objects.unlink(region)
    bpy.context.view_layer.update()
    bpy.context.view_layer.objects.active = nerf
    assert bpy.ops.nerf_deform.extract_mesh() == {"FINISHED"}
    surface = nerf.nerf_deform.surface
    co = _co(surface.data)
    assert nerf.nerf_deform.edit_region is None and extracted_region(surface) is None
    # (The briefly trained NeRF's top is faint: at the threshold its mesh reaches z ~ 0.35 there.)
    assert co[:, 2].min() < -0.6 and co[:, 2].max() > 0.2
    assert not cut_flags(surface.data).any()  # the sphere lies inside the box: nothing cut
