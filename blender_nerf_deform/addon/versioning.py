"""The add-on's data in saved .blend files across releases: one data version, and the repairs of older files.

As Cycles keeps one `version_update.py` whose `do_versions` upgrades what older files hold, keyed on
the version that saved them, every repair of data an older release of this add-on left in a file
lives here. Each scene stores `Scene.nerf_deform_data_version`, set to DATA_VERSION when the file
is saved (not on load: a file just opened, the startup file included, stays unmodified). A file's
version is the highest of its scenes'; a file saved before the version existed stores none and is
version 0, the oldest. On load, `do_versions` runs, in order, every repair newer than the file's
version. Data linked from another file is not ours to change and is left as it is.

A new repair: raise DATA_VERSION, write the function (it must be safe on any file of an older
version) and add it to `REPAIRS` under the new version. Fixtures: addon_tests/fixtures/unversioned.blend
is a file of version 0 (addon_tests/addon/test_versioning.py opens and renders it).

It sits beside api.py, above the layers (tools/check_layering.py: ADDON_TOP), and reads and repairs
the data layer's stored data only. What runs on every load stays with its module, since it is no
upgrade of old data:
data/properties.py's `forget_deleted` (pointers to objects the artist deleted, in a file of any
version), deform/handles.py's region cache (this session's memory, not the file's data),
render/prewarm.py's start of the worker, and edit/regions.py's reading of a region that only the
NeRF's `edit_region` pointer names (a script can still make one, so it is read as a region always).
"""

from __future__ import annotations

from collections.abc import Callable

import bpy
from bpy.app.handlers import persistent
from bpy.props import IntProperty

from .data.cage_store import repair_selection_attributes
from .data.properties import Role, add_app_handlers, keep_out_of_renders, remove_app_handlers

DATA_VERSION = 1
VERSION_PROPERTY = "nerf_deform_data_version"


def _repair_mesh_selection() -> None:
    """Version 1: surfaces and cages extracted or built before `repair_selection_attributes` hold an
    ".select_edge" attribute of the wrong type (bpy 5.0.1's `Mesh.update`), and selecting one of their
    edges crashes Blender."""
    for obj in bpy.data.objects:
        if obj.type == "MESH" and obj.nerf_deform.role in (Role.SURFACE, Role.CAGE) and obj.data.library is None:
            repair_selection_attributes(obj.data)


def _cages_into_render_depsgraphs() -> None:
    """Version 1: cages built before `keep_out_of_renders` were `hide_render`, so F12's depsgraph left
    them out and never applied their modifiers."""
    for obj in bpy.data.objects:
        if obj.nerf_deform.role == Role.CAGE and obj.hide_render and obj.library is None:
            keep_out_of_renders(obj)


# (the version whose files no longer need it, repair), oldest first.
REPAIRS: tuple[tuple[int, Callable[[], None]], ...] = (
    (1, _repair_mesh_selection),
    (1, _cages_into_render_depsgraphs),
)


def file_data_version() -> int:
    """The data version of the open file: the highest its own scenes store (0: none stores one)."""
    return max((getattr(s, VERSION_PROPERTY) for s in bpy.data.scenes if s.library is None), default=0)


def do_versions(version: int) -> list[str]:
    """Upgrade the open file's data from `version` to DATA_VERSION: every repair newer than it, in
    order. Returns the names of the repairs that ran."""
    ran = []
    for needed_below, repair in REPAIRS:
        if version < needed_below:
            repair()
            ran.append(repair.__name__.lstrip("_"))
    return ran


def _stamp() -> None:
    for scene in bpy.data.scenes:
        if scene.library is None and getattr(scene, VERSION_PROPERTY) != DATA_VERSION:
            setattr(scene, VERSION_PROPERTY, DATA_VERSION)


@persistent
def _versions_on_load(*_args) -> None:
    do_versions(file_data_version())


@persistent
def _version_on_save(*_args) -> None:
    _stamp()


def _handlers():
    h = bpy.app.handlers
    return ((h.load_post, _versions_on_load), (h.save_pre, _version_on_save))


def register():
    setattr(
        bpy.types.Scene,
        VERSION_PROPERTY,
        IntProperty(
            name="NeRF Deform Data Version",
            description="Version of the NeRF Deform data in this file, which the add-on upgrades on load",
            default=0,
            min=0,
            options=set(),  # not animatable
        ),
    )
    add_app_handlers(_handlers())


def unregister():
    remove_app_handlers(_handlers())
    delattr(bpy.types.Scene, VERSION_PROPERTY)
