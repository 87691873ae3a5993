"""Saved .blend files across releases (addon/versioning.py): a file saved before the data version
opens upgraded and renders as a file saved by this release does."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from fixtures import REPO
from PIL import Image

UNVERSIONED = REPO / "addon_tests" / "fixtures" / "unversioned.blend"


def _render(bpy, path) -> np.ndarray:
    """F12 through the add-on's render engine, as an 8-bit RGBA array."""
    scene = bpy.context.scene
    assert scene.render.engine == "NERF_DEFORM"
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGBA"
    scene.render.filepath = str(path)
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    return np.asarray(Image.open(path).convert("RGBA"))


def _nerf(bpy):
    (nerf,) = [o for o in bpy.data.objects if o.nerf_deform.role == "NERF"]
    return nerf


def _select_edge_types(mesh) -> set[str]:
    attribute = mesh.attributes.get(".select_edge")
    return set() if attribute is None else {attribute.data_type}


@pytest.mark.slow
def test_a_file_saved_before_the_data_version_opens_upgraded_and_renders_as_one_saved_now(addon, sphere_nerf, tmp_path):
    bpy = addon
    from blender_nerf_deform.addon.data.properties import RAY_VISIBILITY
    from blender_nerf_deform.addon.versioning import DATA_VERSION, VERSION_PROPERTY, file_data_version

    ckpt, _ = sphere_nerf
    old = tmp_path / "old.blend"
    shutil.copyfile(UNVERSIONED, old)
    assert bpy.ops.wm.open_mainfile(filepath=str(old)) == {"FINISHED"}
    assert file_data_version() == 0  # as saved: no version
    nerf = _nerf(bpy)
    s = nerf.nerf_deform
    cage, surface = s.cage, s.surface
    # Upgraded on load: the cage in render depsgraphs (its Twist modifier applies in F12), the meshes'
    # edge selection of the right type.
    assert not cage.hide_render and not any(getattr(cage, flag) for flag in RAY_VISIBILITY)
    assert _select_edge_types(cage.data) <= {"BOOLEAN"} and _select_edge_types(surface.data) <= {"BOOLEAN"}
    assert s.deformation_mode == "MODIFIERS" and cage.modifiers["Twist"].show_render

    s.checkpoint = str(ckpt)  # the path it stores is the machine's that made it
    bent = _render(bpy, tmp_path / "old_bent.png")
    cage.modifiers["Twist"].show_render = False
    rest = _render(bpy, tmp_path / "old_rest.png")
    cage.modifiers["Twist"].show_render = True
    assert bent[..., 3].max() > 120 and bent[..., 3].min() < 20  # the NeRF and empty space in view
    assert np.abs(bent.astype(np.int16) - rest).max() > 60  # the twist bends the frame

    # Saved by this release: the version is written, and the file renders the same frame, bit for bit.
    current = tmp_path / "current.blend"
    assert bpy.ops.wm.save_as_mainfile(filepath=str(current)) == {"FINISHED"}
    assert bpy.ops.wm.open_mainfile(filepath=str(current)) == {"FINISHED"}
    assert file_data_version() == DATA_VERSION
    assert all(getattr(scene, VERSION_PROPERTY) == DATA_VERSION for scene in bpy.data.scenes)
    assert np.array_equal(_render(bpy, tmp_path / "current_bent.png"), bent)


def test_repairs_run_on_files_older_than_them_only(addon, tmp_path):
    """An unversioned file gets every repair; in a file of this version a cage the artist hid from
    renders stays hidden (the repair is an upgrade of old files, not a rule of every load)."""
    bpy = addon
    import blender_nerf_deform
    from blender_nerf_deform.addon.versioning import DATA_VERSION, do_versions, file_data_version

    def scene_with_hidden_cage():
        bpy.ops.wm.read_factory_settings(use_empty=True)
        cage = bpy.data.objects.new("Cage", bpy.data.meshes.new("Cage"))
        bpy.context.scene.collection.objects.link(cage)
        cage.nerf_deform.role = "CAGE"
        cage.hide_render = True

    # Made with the add-on, saved without it (as a release before the version saved it: no version).
    scene_with_hidden_cage()
    blender_nerf_deform.unregister()
    try:
        bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "old.blend"))
    finally:
        blender_nerf_deform.register()
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "old.blend"))
    assert file_data_version() == 0 and not bpy.data.objects["Cage"].hide_render

    scene_with_hidden_cage()
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "new.blend"))
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "new.blend"))
    assert file_data_version() == DATA_VERSION and bpy.data.objects["Cage"].hide_render
    assert do_versions(DATA_VERSION) == []
    assert do_versions(0) == ["repair_mesh_selection", "cages_into_render_depsgraphs"]
