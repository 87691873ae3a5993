"""Edit regions from the add-on: the box Empty and its REGION dict, Extract Mesh inside it (the cut
flagged), Build Cage pinned at the cut, ARAP keeping the pins, and the errors of bad regions and
picks. Real headless Blender and the real worker."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from fixtures.blender_objects import select_in_edit_mode

BOX = (-1.5, -1.5, -1.5, 1.5, 1.5, 1.5)


def nerf_with_sphere_surface(bpy, ckpt=None):
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

    from blender_nerf_deform.addon.edit.regions import edit_region_of
    from blender_nerf_deform.engine.geometry.region import region_from_dict

    nerf = nerf_with_sphere_surface(bpy)
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

    # A second Add Edit Region adds a second region (one object, and one cage, each), around the
    # cursor; the NeRF's `edit_region` is the one added last.
    from blender_nerf_deform.addon.edit.regions import regions_of

    n_objects = len(bpy.data.objects)
    second = _add_region(bpy, nerf)
    assert second != region and len(bpy.data.objects) == n_objects + 1
    assert regions_of(nerf) == sorted([region, second], key=lambda o: o.name)


def test_a_new_region_with_the_cursor_outside_the_box_covers_the_whole_box(addon):
    bpy = addon
    from blender_nerf_deform.addon.edit.regions import edit_region_of

    nerf = nerf_with_sphere_surface(bpy)
    nerf.nerf_deform.aabb = (-1.0, -2.0, 0.0, 3.0, 2.0, 1.0)
    bpy.context.scene.cursor.location = (5.0, 0.0, 0.0)
    _add_region(bpy, nerf)
    bpy.context.view_layer.update()
    d = edit_region_of(nerf)
    assert np.allclose(d["center"], [1.0, 0.0, 0.5], atol=1e-6) and np.allclose(d["size"], [4.0, 4.0, 1.0], atol=1e-5)
    # A second one would overlap a whole-box first: a third of the box at its middle (still added;
    # Extract Mesh reports the overlap).
    _add_region(bpy, nerf)
    bpy.context.view_layer.update()
    d = edit_region_of(nerf)
    assert np.allclose(d["center"], [1.0, 0.0, 0.5], atol=1e-6) and np.allclose(
        d["size"], [4 / 3, 4 / 3, 1 / 3], atol=1e-5
    )


def test_regions_without_a_box_are_refused_before_anything_is_extracted(addon):
    bpy = addon
    nerf = nerf_with_sphere_surface(bpy)  # no checkpoint: the region is checked before the worker is asked anything
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
    from blender_nerf_deform.addon.edit.regions import edit_region_of

    region.parent, region.rotation_euler, region.scale = nerf, (0.0, 0.0, 0.0), (-0.5, 1.0, 1.0)
    bpy.context.view_layer.update()
    assert np.allclose(edit_region_of(nerf)["size"], [0.5, 1.0, 1.0], atol=1e-6)


def test_a_deleted_region_is_forgotten_and_the_region_survives_save_and_reopen(addon, tmp_path):
    bpy = addon
    from blender_nerf_deform.addon.data.properties import forget_deleted
    from blender_nerf_deform.addon.edit.regions import edit_region_of

    nerf = nerf_with_sphere_surface(bpy)
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
    from blender_nerf_deform.addon.data.cage_store import CUT_PIN_GROUP, cage_pins, load_cage, load_embedding
    from blender_nerf_deform.addon.data.mesh_attributes import cut_flags
    from blender_nerf_deform.addon.deform.handles import group_vertices
    from blender_nerf_deform.addon.deform.poses import deformed_cage
    from blender_nerf_deform.addon.edit.regions import edit_region_of, extracted_regions
    from blender_nerf_deform.addon.worker import jobs

    ckpt, _ = sphere_nerf
    nerf = nerf_with_sphere_surface(bpy, ckpt)
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
    assert extracted_regions(surface) == [edit_region_of(nerf)]

    bpy.context.view_layer.objects.active = nerf
    assert bpy.ops.nerf_deform.build_cage() == {"FINISHED"}
    cage = nerf.nerf_deform.cage
    rest, tets = load_cage(cage.data)
    pins = cage_pins(cage)
    assert len(pins) > 10 and np.array_equal(np.sort(group_vertices(cage, CUT_PIN_GROUP)), pins)
    # The cage's side at the cut and the rim around it, far from its bottom.
    assert rest[pins, 2].min() > -0.5 and rest[:, 2].min() < -0.8 and np.abs(rest[pins, 2]).mean() < 0.25

    # A handle on the bottom moved down: ARAP keeps the pinned cage vertices at rest (soft pins: within
    # a thousandth of the cage's size), the cut stays.
    bottom = np.flatnonzero(co[:, 2] < -0.6)
    select_in_edit_mode(bpy, surface, bottom)
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
    assert np.linalg.norm(deformed[pins] - rest[pins], axis=1).max() < 1e-3 * np.linalg.norm(np.ptp(rest, axis=0))
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
    assert extracted_regions(nerf.nerf_deform.surface) == [edit_region_of(nerf)]


@pytest.mark.slow
def test_bad_regions_and_picks_get_the_workers_error_and_leave_the_scene_alone(addon, sphere_nerf):
    bpy = addon
    from blender_nerf_deform.addon.data.mesh_attributes import cut_flags
    from blender_nerf_deform.addon.edit.regions import extracted_regions

    ckpt, _ = sphere_nerf
    nerf = nerf_with_sphere_surface(bpy, ckpt)
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
    assert nerf.nerf_deform.edit_region is None and extracted_regions(surface) == []
    # (The briefly trained NeRF's top is faint: at the threshold its mesh reaches z ~ 0.35 there.)
    assert co[:, 2].min() < -0.6 and co[:, 2].max() > 0.2
    assert not cut_flags(surface.data).any()  # the sphere lies inside the box: nothing cut


def test_a_single_region_file_still_counts_its_region_and_its_recorded_region(addon):
    """Files of the single-region version: the NeRF's `edit_region` pointer (even to an Empty not
    marked as a region of it) counts, and a surface's recorded region is one REGION dict."""
    bpy = addon
    import json

    from blender_nerf_deform.addon.edit.regions import (
        SURFACE_REGION_KEY,
        edit_regions_of,
        extracted_regions,
        regions_of,
    )

    nerf = nerf_with_sphere_surface(bpy)
    old = bpy.data.objects.new("Old Region", None)
    old.empty_display_type = "CUBE"
    bpy.context.scene.collection.objects.link(old)
    old.parent = nerf
    nerf.nerf_deform.edit_region = old
    assert regions_of(nerf) == [old] and len(edit_regions_of(nerf)) == 1
    new = _add_region(bpy, nerf)  # a second one beside it: both count, by name
    assert regions_of(nerf) == sorted([old, new], key=lambda o: o.name) and nerf.nerf_deform.edit_region == new

    mesh = bpy.data.meshes.new("Surface")
    surface = bpy.data.objects.new("Surface", mesh)
    one = {"center": [0.0, 0.1, 0.2], "size": [1.0, 1.0, 1.0], "rotation_euler": [0.0, 0.0, 0.0]}
    for text, expected in (
        (json.dumps(one), [one]),
        (json.dumps([one, one]), [one, one]),
        ("", []),
        ("not json", []),
        ("[1, 2]", []),
        ('"text"', []),
    ):
        mesh[SURFACE_REGION_KEY] = text
        assert extracted_regions(surface) == expected, text


def test_cage_vertex_parts_follow_the_pieces_the_surface_is_embedded_in():
    from blender_nerf_deform.addon.data.cage_store import cage_vertex_parts

    # Two pieces (vertices 0-4 and 5-9, two tets each) and a stray tet (10-13) holding no surface vertex.
    tets = np.array([[0, 1, 2, 3], [1, 2, 3, 4], [5, 6, 7, 8], [6, 7, 8, 9], [10, 11, 12, 13]])
    tet_ids = np.array([0, 1, 1, 2, 3, 3])
    surface_part = np.array([2, 2, 0, 5, 5, 5])  # piece 0: mostly part 2; piece 1: part 5
    part = cage_vertex_parts(14, tets, tet_ids, surface_part)
    assert part.tolist() == [2] * 5 + [5] * 5 + [5] * 4
    assert (cage_vertex_parts(4, tets[:1], np.zeros(0, int), np.zeros(0, int)) == -1).all()


def _two_region_camera(bpy, size=40):
    """A camera on the -y side looking along +y at the sphere: image columns left of the middle see x < 0."""
    scene = bpy.context.scene
    cam_data = bpy.data.cameras.new("Camera")
    cam_data.sensor_fit, cam_data.angle_x = "HORIZONTAL", 0.75
    camera = bpy.data.objects.new("Camera", cam_data)
    scene.collection.objects.link(camera)
    scene.camera = camera
    camera.location, camera.rotation_euler = (0.0, -4.0, -0.3), (math.pi / 2, 0.0, 0.0)
    scene.render.resolution_x = scene.render.resolution_y = size
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGBA"
    scene.render.image_settings.color_depth = "8"


def _render(bpy, path):
    from PIL import Image

    bpy.context.scene.render.filepath = str(path)
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    return np.asarray(Image.open(path).convert("RGBA"), dtype=np.int16)


@pytest.mark.slow
def test_two_regions_two_objects_each_with_its_own_cage_handle_and_render(addon, sphere_nerf, tmp_path):
    """Issue 14: two objects of one NeRF (the sphere's left and right lower parts) edited
    separately: one mesh with two parts, one cage with two pieces, each pinned at its own cut; a
    handle on the left part moves the left piece only, and the frame changes on the left only."""
    bpy = addon
    from blender_nerf_deform.addon.data.cage_store import cage_pins, load_cage
    from blender_nerf_deform.addon.data.mesh_attributes import cut_flags, part_labels
    from blender_nerf_deform.addon.deform.poses import deformed_cage
    from blender_nerf_deform.addon.edit.regions import edit_regions_of, extracted_regions, regions_of, same_regions
    from blender_nerf_deform.addon.worker import jobs

    ckpt, _ = sphere_nerf
    nerf = nerf_with_sphere_surface(bpy, ckpt)
    left = _add_region(bpy, nerf)
    right = _add_region(bpy, nerf)
    assert regions_of(nerf) == [left, right]  # by name: "... Region", "... Region.001"

    # Overlapping: the engine's error, the regions named, and nothing made.
    _place(bpy, left, (-0.4, 0.0, -0.35), (0.8, 2.0, 1.1))
    _place(bpy, right, (0.2, 0.0, -0.35), (0.8, 2.0, 1.1))
    n_objects = len(bpy.data.objects)
    bpy.context.view_layer.objects.active = nerf
    with pytest.raises(
        RuntimeError, match=rf"edit regions 1 and 2 overlap.*1: {re.escape(left.name)}, 2: {re.escape(right.name)}"
    ):
        bpy.ops.nerf_deform.extract_mesh()
    assert nerf.nerf_deform.surface is None and len(bpy.data.objects) == n_objects

    # Apart: x in [-0.9, -0.45] and [0.45, 0.9], z in [-0.9, 0.2] (the sphere's dense lower sides; far
    # enough apart that the two cages do not meet: the briefly trained NeRF's soft density widens
    # each cage's margin, and its envelope reaches ~0.4 beyond the cut).
    _place(bpy, left, (-0.675, 0.0, -0.35), (0.45, 2.0, 1.1))
    _place(bpy, right, (0.675, 0.0, -0.35), (0.45, 2.0, 1.1))
    bpy.context.view_layer.objects.active = right  # any part of the NeRF will do
    assert bpy.ops.nerf_deform.extract_mesh() == {"FINISHED"}
    surface = nerf.nerf_deform.surface
    co, cut, part = _co(surface.data), cut_flags(surface.data), part_labels(surface.data)
    assert part is not None and sorted(np.unique(part)) == [0, 1]
    assert same_regions(extracted_regions(surface), edit_regions_of(nerf))
    for i, sign in ((0, -1.0), (1, 1.0)):
        mine = part == i
        assert mine.sum() > 50 and (sign * co[mine, 0]).min() > 0.05, i  # each part on its own side
        inner = mine & cut & (np.abs(co[:, 0] - sign * 0.45) < 0.06)  # closed along its inner face x = ±0.45
        assert inner.sum() > 10, i
        on_faces = (np.abs(co[:, 0] - sign * 0.45) < 0.06) | (np.abs(co[:, 2] - 0.2) < 0.06)
        assert on_faces[mine & cut].all(), i  # the cut lies on the faces that cut the sphere

    bpy.context.view_layer.objects.active = nerf
    assert bpy.ops.nerf_deform.build_cage() == {"FINISHED"}
    cage = nerf.nerf_deform.cage
    rest, tets = load_cage(cage.data)
    cage_part, pins = part_labels(cage.data), cage_pins(cage)
    assert cage_part is not None and sorted(np.unique(cage_part)) == [0, 1]
    assert (cage_part[tets] == cage_part[tets[:, :1]]).all()  # no tet joins the two pieces
    left_x, right_x = rest[cage_part == 0, 0], rest[cage_part == 1, 0]
    assert left_x.max() < right_x.min(), (left_x.max(), right_x.min())  # side by side, apart
    assert (np.bincount(cage_part[pins], minlength=2) > 5).all()  # pinned at both cuts

    # A handle on the left part's outer side, moved down.
    from fixtures.blender_objects import select_in_edit_mode

    outer_left = np.flatnonzero((part == 0) & (co[:, 0] < -0.65))
    select_in_edit_mode(bpy, surface, outer_left)
    assert bpy.ops.nerf_deform.add_handle() == {"FINISHED"}
    handle = bpy.context.active_object

    _two_region_camera(bpy)
    bpy.context.scene.render.engine = "NERF_DEFORM"
    at_rest = _render(bpy, tmp_path / "rest.png")
    handle.location.z -= 0.25
    bpy.context.view_layer.update()
    deformed = deformed_cage(nerf, bpy.context.evaluated_depsgraph_get(), jobs.worker(bpy.context))
    assert np.abs(deformed[cage_part == 1] - rest[cage_part == 1]).max() < 1e-9  # the right piece at rest
    assert np.abs(deformed[cage_part == 0] - rest[cage_part == 0]).max() > 0.15  # the left one moved
    moved = _render(bpy, tmp_path / "moved.png")

    # The columns whose rays never reach the left piece (rest or moved): x = (y + 4) tan(angle) stays
    # right of it for y >= the cage's nearest y.
    w = at_rest.shape[1]
    reach = max(rest[cage_part == 0, 0].max(), deformed[cage_part == 0, 0].max())
    depth = 4.0 + min(rest[:, 1].min(), deformed[:, 1].min())
    column_x = (np.arange(w) + 0.5 - w / 2) / (w / 2) * math.tan(0.75 / 2)  # x per unit of depth
    clear = column_x * depth > reach + 0.02
    assert clear.sum() > w // 3, (reach, depth)
    assert at_rest[:, clear, 3].max() > 120  # the right object is in view there
    diff = np.abs(moved - at_rest).max(axis=-1)
    assert diff[:, : w // 2 - 2].max() > 60  # the left object moved
    assert diff[:, clear].max() <= 2  # the right object renders as at rest

    # Saved and reopened: both regions, the parts of the mesh and of the cage, the pins.
    before = edit_regions_of(nerf)
    blend = tmp_path / "two.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    nerf = next(o for o in bpy.data.objects if o.nerf_deform.role == "NERF")
    regions = regions_of(nerf)
    assert len(regions) == 2 and same_regions(edit_regions_of(nerf), before)
    surface, cage = nerf.nerf_deform.surface, nerf.nerf_deform.cage
    assert np.array_equal(part_labels(surface.data), part) and np.array_equal(part_labels(cage.data), cage_part)
    assert np.array_equal(cage_pins(cage), pins) and same_regions(extracted_regions(surface), before)


def test_add_handle_says_when_its_vertices_span_two_regions_objects(addon, capfd):
    bpy = addon
    from fixtures.blender_objects import nerf_with_grid_surface

    from blender_nerf_deform.addon.data.mesh_attributes import part_labels, set_part_labels

    nerf, surface, verts = nerf_with_grid_surface(bpy)
    set_part_labels(surface.data, (verts[:, 0] > 0).astype(np.int32))  # two objects: x <= 0 and x > 0
    assert np.array_equal(part_labels(surface.data), verts[:, 0] > 0)
    with pytest.raises(ValueError, match="3 part labels for a mesh of 125 vertices"):
        set_part_labels(surface.data, np.zeros(3))

    select_in_edit_mode(bpy, surface, np.flatnonzero(verts[:, 0] < -0.4))  # one object's side
    assert bpy.ops.nerf_deform.add_handle() == {"FINISHED"}
    assert "span the objects" not in capfd.readouterr().out
    select_in_edit_mode(bpy, surface, np.flatnonzero((verts[:, 2] > 0.4) & (verts[:, 0] > -0.4)))  # the top of both
    assert bpy.ops.nerf_deform.add_handle() == {"FINISHED"}
    assert "vertices span the objects of 2 edit regions (parts 1, 2)" in capfd.readouterr().out
